"""The session API: plan, run, resume and inspect a measurement session.

>>> dry = plan_session(plan, rig_config)                                  # doctest: +SKIP
>>> result = run_session("S/", plan, rig_config, open_devices, dry_run=dry)  # doctest: +SKIP
>>> result = resume_session("S/", open_devices, retake=True)             # doctest: +SKIP
>>> report = inspect_session("S/")                                       # doctest: +SKIP

``devices`` is either open :class:`~gonio.capture.engine.SessionDevices` or a *device
opener*: a callable taking a :class:`DeviceRequest` (what the session needs: rig
configuration, camera backend, seed, simulation record) and returning a context manager
of :class:`SessionDevices`.  The composition root (``gonio.app.devices``) provides the
opener for real and simulated rigs; with an opener, the session lock is taken *before*
anything is opened, so a second process refused by the lock never touches the rig.

A run is the plan of :mod:`gonio.capture.session_plan` executed by the engine of
:mod:`gonio.capture.engine`; the journal and any ``subscribers`` (progress displays)
receive its documents.  Nothing here prints.

One process at a time: :func:`run_session` and :func:`resume_session` hold
:func:`gonio.locks.hold_lock` on ``SESSION/.gonio.lock`` (and, while the session is
being created, on ``.NAME.gonio.lock`` beside it) for their whole run; a second one
raises :class:`~gonio.locks.LockedError` naming the holder's PID and writes nothing.
"""

from __future__ import annotations

import contextlib
import shutil
from collections.abc import Callable, Mapping, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gonio import __version__
from gonio.capture.adaptive import ROUND, adaptive_session_plan, adaptive_steps
from gonio.capture.adaptive_pool import POOL_FILE, read_pool
from gonio.capture.engine import Engine, SessionDevices, Subscriber, run_plan
from gonio.capture.journal import Journal, read_journal, session_file, write_atomic
from gonio.capture.manifest import Manifest, check_journal_fits, read_manifest
from gonio.capture.plan import Plan, plan_digest
from gonio.capture.schedule import Refusal, Schedule, StageProgress, build_schedule
from gonio.capture.session_dir import (
    JOURNAL,
    BadFrame,
    SessionState,
    check_new_session_dir,
    create_session,
    session_state,
    verify_frames,
)
from gonio.capture.session_plan import RAW_DIR, session_plan
from gonio.capture.session_report import SessionReport, inspect_session
from gonio.errors import CameraError, SessionError
from gonio.locks import LOCK_NAME, hold_lock

__all__ = [
    "DeviceOpener",
    "DeviceRequest",
    "DryRun",
    "RunResult",
    "SessionReport",
    "SessionStopped",
    "SkippedPose",
    "check_calibration_devices",
    "inspect_session",
    "plan_session",
    "resume_session",
    "run_session",
]


@dataclass(frozen=True)
class DeviceRequest:
    """What a device opener is asked to open for a session.

    Attributes
    ----------
    session_dir
        The session (for a new run: where it will be).
    rig_config
        The rig configuration to open (``gonio.rig.config.RigConfig``).
    camera_backend
        ``"gphoto2"``, ``"simulated"``, ...
    plan
        The session's plan.
    seed
        The session seed (the virtual bus's faults, the simulated camera's noise).
    simulation
        The manifest's simulation record (scene paths relative to ``session_dir``),
        None for a real camera.
    reference_reflectance
        The reference target's reflectance (the simulated camera renders it).
    """

    session_dir: Path
    rig_config: Any
    camera_backend: str
    plan: Plan
    seed: int
    simulation: Mapping[str, Any] | None = None
    reference_reflectance: Any = None


DeviceOpener = Callable[[DeviceRequest], AbstractContextManager[SessionDevices]]


@dataclass
class DryRun:
    """The dry run of a plan on a rig: the schedule and what it would need."""

    plan: Plan
    rig_config: Any
    schedule: Schedule

    @property
    def steps(self) -> list[dict[str, Any]]:
        return self.schedule.steps

    @property
    def refused(self) -> list[Refusal]:
        return self.schedule.refused

    def summary(self, with_poses: bool = False) -> dict[str, Any]:
        """The figures ``gonio capture plan --json`` prints."""
        sched, ex = self.schedule, self.schedule.expanded
        out: dict[str, Any] = {
            "plan": self.plan.name,
            "grid_poses": ex.n_grid,
            "reduced_by_symmetry": ex.n_reduced,
            "excluded": len(ex.excluded),
            "sample_poses": sum(1 for s in sched.steps if s["kind"] == "sample"),
            "reference_poses": sum(1 for s in sched.steps if s["kind"] == "reference"),
            "dark_steps": sum(1 for s in sched.steps if s["kind"] == "dark"),
            "flat_steps": sum(1 for s in sched.steps if s["kind"] == "flat"),
            "travel_time_s": round(sched.travel_time_s, 3),
            "raster_travel_time_s": round(sched.raster_travel_time_s, 3),
            "estimated_duration_s": round(sched.estimated_duration_s, 1),
            "excluded_poses": [
                {**e.pose.angles_deg(), "reason": e.reason, "code": e.code} for e in ex.excluded
            ],
            "refused_in_order": [
                {"step": r.step, "code": r.code, "reason": r.message} for r in sched.refused
            ],
        }
        if self.plan.adaptive is not None and sched.pool is not None:
            a = self.plan.adaptive
            out["adaptive"] = {
                "pool": len(sched.pool),
                "seed_poses": a.seed_poses,
                "batch_poses": a.batch_poses,
                "max_poses": a.max_poses,
                "max_time_s": a.max_time_s,
                "candidates": list(a.candidates),
                "target_rel_sigma": dict(a.target_rel_sigma),
                "target_brdf_rel_sigma": a.target_brdf_rel_sigma,
            }
        if self.plan.is_joint_pose_plan:
            out["joint_poses"] = len(self.plan.joint_poses)
            out["mirror_poses"] = sum(1 for s in sched.steps if s["kind"] == "mirror")
        if with_poses:
            out["poses"] = [
                {k: s[k] for k in s if k.endswith("_deg") or k in ("kind", "label")}
                for s in sched.steps
            ]
        return out


@dataclass(frozen=True)
class SkippedPose:
    """A pose the rig refused before moving (``code``: a ``RefusalReason`` value)."""

    pose: int
    reason: str
    code: str | None = None


@dataclass
class RunResult:
    """How a run or resume ended.

    Attributes
    ----------
    session
        The session directory.
    status
        ``"completed"``, ``"fault"`` or ``"interrupted"``.
    poses_total, poses_done
        Steps in the schedule, and closed ones (done or skipped) after the run.
    shots
        Frames shot by this run.
    skipped
        Poses skipped by this run.
    retaken
        Files of the frames this run shot again (``retake``).
    finalizer
        What the finalizer reported (``parked``, ``torque_off``, ...).
    adaptive_stop
        An adaptive session's stop (its last round: ``round``, ``stop``, ``poses_done``).
    """

    session: Path
    status: str
    poses_total: int
    poses_done: int
    shots: int = 0
    skipped: list[SkippedPose] = field(default_factory=list)
    retaken: list[str] = field(default_factory=list)
    finalizer: dict[str, Any] = field(default_factory=dict)
    #: An adaptive session's stop: ``{"round", "stop", "poses_done"}`` of its last round
    #: (None before it stopped, or for a grid).
    adaptive_stop: dict[str, Any] | None = None


class SessionStopped(SessionError):
    """A run stopped on a fault or an interrupt; ``result`` says what was done."""

    def __init__(self, message: str, result: RunResult) -> None:
        self.result = result
        super().__init__(message)


# --------------------------------------------------------------------------------------


def _check_target_changer(
    steps: Sequence[Mapping[str, Any]], devices: SessionDevices, plan: Plan
) -> None:
    """A step of kind "mirror" needs something that puts the mirror in place: refused
    before anything moves or is written when the devices have none."""
    n = sum(1 for s in steps if s.get("kind") == "mirror")
    if n and devices.target is None:
        raise SessionError(
            f"plan {plan.name!r}: {n} step(s) view the calibration mirror (target = "
            "'mirror') but these devices have no target changer to put it in the sample's "
            "place; use a rig that has one (the simulated camera, or an operator prompt) "
            "(nothing was moved or written)"
        )


def check_calibration_devices(
    plan: Plan, has_light: bool, has_target: bool, *, resumed: bool = False
) -> None:
    """Dark frames need a light switch, flat fields a target changer (the panel over the
    lens): refused before anything moves (or is written) when the devices lack them.

    Raises
    ------
    SessionError
        Naming the plan table, the count and the option that gives the device.
    """
    after = " (nothing was moved or written)" if not resumed else " (nothing was moved)"
    if plan.darks.count and not has_light:
        raise SessionError(
            f"plan {plan.name!r}: [darks] count = {plan.darks.count} needs the rig's light "
            "switched off, and these devices have no light switch: give --light "
            "relay:PORT (a serial relay) or --light operator (you switch it when asked), "
            "or set [darks] count = 0 and shoot darks with the lens capped" + after
        )
    if plan.flats.count and not has_target:
        raise SessionError(
            f"plan {plan.name!r}: [flats] count = {plan.flats.count} needs a target changer "
            "to put the flat-field panel over the lens, and these devices have none (the "
            "simulated camera has one); set [flats] count = 0 and shoot flats apart" + after
        )


def plan_session(
    plan: Plan,
    rig_config: Any,
    *,
    start_joints: Mapping[str, float] | None = None,
    progress: StageProgress | None = None,
) -> DryRun:
    """Dry-run ``plan`` on the rig of ``rig_config``: nothing moves.

    Parameters
    ----------
    plan
        The validated plan.
    rig_config
        ``gonio.rig.config.RigConfig``.
    start_joints
        Where the rig starts (default: its park pose), rad.
    progress
        ``progress(stage, done, total)`` on a long dry run
        (:data:`gonio.capture.schedule.StageProgress`).

    Raises
    ------
    SessionError
        No pose of the plan is reachable.
    """
    from gonio.rig.kinematics import Kinematics

    kin = Kinematics(rig_config)
    start = dict(start_joints) if start_joints is not None else rig_config.park_rad
    return DryRun(plan, rig_config, build_schedule(plan, kin, start, progress))


def _enter(
    devices: SessionDevices | DeviceOpener, request: DeviceRequest, stack: contextlib.ExitStack
) -> SessionDevices:
    if isinstance(devices, SessionDevices):
        return devices
    return stack.enter_context(devices(request))


def run_session(
    out: str | Path,
    plan: Plan,
    rig_config: Any,
    devices: SessionDevices | DeviceOpener,
    *,
    camera_backend: str = "gphoto2",
    dry_run: DryRun | None = None,
    simulation: Mapping[str, Any] | None = None,
    attachments: Mapping[str, str | Path] | None = None,
    subscribers: Sequence[Subscriber] = (),
    advisor: Any = None,
) -> RunResult:
    """Create the session ``out`` and run it.

    Parameters
    ----------
    out
        The new session directory (must not exist, or be empty).
    plan, rig_config
        The plan and the rig configuration.
    devices
        Open devices, or a device opener (see the module docstring).
    camera_backend
        Passed to the opener.
    dry_run
        The plan's :func:`plan_session` (computed when None).
    simulation
        The simulation record for the manifest (simulated sessions).
    attachments
        Path inside the session -> file, copied in at creation (a scene's files).
    subscribers
        Called with every document after the journal has it.
    advisor
        An ``[adaptive]`` plan's :class:`gonio.capture.adaptive.Advisor`, or a callable
        ``advisor(plan) -> Advisor`` (required for such a plan, ignored otherwise).

    Raises
    ------
    SessionError
        ``out`` holds something, the plan needs a light the devices lack, an adaptive
        plan has no advisor (nothing is written), or the run stopped on a fault or an
        interrupt (:class:`SessionStopped`, after the finalizer; resume it).
    LockedError
        Another process is creating a session at ``out``.
    """
    out = Path(out)
    check_new_session_dir(out)  # before anything slow or physical
    _check_advisor(plan, advisor)
    dry = dry_run if dry_run is not None else plan_session(plan, rig_config)
    out.parent.mkdir(parents=True, exist_ok=True)
    beside = out.parent / f".{out.name}{LOCK_NAME}"
    request = DeviceRequest(
        out, rig_config, camera_backend, plan, plan.seed, simulation, plan.reference.reflectance
    )
    with contextlib.ExitStack() as locks:
        locks.enter_context(hold_lock(beside, f"session {out}"))
        # Removed while still held, whatever happens (a refused run leaves nothing; once
        # the session exists, its own lock guards it).
        locks.callback(beside.unlink, missing_ok=True)
        check_new_session_dir(out)  # again: another process may have made it meanwhile
        for stale in out.parent.glob(f".{out.name}.creating-*"):  # our kind, cut by a kill
            shutil.rmtree(stale, ignore_errors=True)
        with contextlib.ExitStack() as opened:
            dev = _enter(devices, request, opened)
            _check_target_changer(dry.steps, dev, plan)
            check_calibration_devices(plan, dev.light is not None, dev.target is not None)
            # The session's own lock goes into the outer stack: it is released after the
            # devices are closed, never while this process still holds the rig.
            create_session(
                out,
                plan,
                rig_config,
                dry.schedule,
                dev.camera.describe(),
                simulation=simulation,
                attachments=attachments,
                hold=locks,
                files={**dev.files, **_pool_file(dry)},
            )
            manifest = read_manifest(out)
            return _run(
                out, manifest, plan, dev, session_state([]), False, {}, subscribers, advisor=advisor
            )


def resume_session(
    session_dir: str | Path,
    devices: SessionDevices | DeviceOpener,
    *,
    plan: Plan | None = None,
    rig_config: Any = None,
    force: bool = False,
    retake: bool = False,
    subscribers: Sequence[Subscriber] = (),
    plan_source: str = "the given plan",
    rig_source: str = "the given rig",
    advisor: Any = None,
) -> RunResult:
    """Continue a session after a fault, a crash or Ctrl-C.

    Poses already closed are passed over; a pose cut short keeps its frames and its
    bracket continues; a RAW file written but never journaled is shot again.  Every
    frame the session relies on is checked first (byte count and XXH3-128; sha256 for
    older records).

    Parameters
    ----------
    session_dir
        The session.
    devices
        Open devices, or a device opener (asked for the manifest's rig and camera).
    plan, rig_config
        When given, compared with the session's; a difference is refused unless
        ``force`` (then recorded in the journal, and the given rig is used).
    retake
        Shoot the frames that failed the check again (journaled as replacements:
        ``"retake": true`` and ``"replaces"``; the newest record of a frame counts).
    subscribers
        Called with every document after the journal has it.
    plan_source, rig_source
        How to name ``plan`` and ``rig_config`` in messages (e.g. their files).
    advisor
        As :func:`run_session` (an adaptive session's rounds not yet journaled).

    Raises
    ------
    SessionError
        Not a session, a damaged manifest or journal (:class:`FileFormatError`, the field
        named), a different plan or rig without ``force``, frames that fail the check
        without ``retake`` (the files named; nothing is written), or the run stopped
        again (:class:`SessionStopped`).
    LockedError
        Another process holds the session.
    """
    d = Path(session_dir)
    read_manifest(d)  # not a session, or a damaged one: refused before any lock file
    with hold_lock(d / LOCK_NAME, f"session {d}"):
        manifest = read_manifest(d)
        _check_advisor(manifest.plan, advisor)
        jp = d / JOURNAL
        records = read_journal(jp) if jp.exists() else []
        check_journal_fits(d, manifest, records)
        state = session_state(records, jp)
        diffs = []
        if plan is not None and plan_digest(plan) != manifest.plan_digest:
            keys = _diff_keys(plan.model_dump(mode="json"), manifest.plan.model_dump(mode="json"))
            diffs.append(f"plan {plan_source} differs from the session's plan ({keys})")
        cfg = manifest.rig
        if rig_config is not None and plan_digest(rig_config) != manifest.rig_digest:
            keys = _diff_keys(
                rig_config.model_dump(mode="json"), manifest.rig.model_dump(mode="json")
            )
            diffs.append(f"rig {rig_source} differs from the session's rig ({keys})")
            if force:
                cfg = rig_config
        if diffs and not force:
            raise SessionError("; ".join(diffs) + ". Refusing to resume; use --force to override")
        bad, _ = verify_frames(d, state, "xxh3")
        if bad and not retake:
            raise SessionError(
                f"{d}: {len(bad)} journaled frame(s) do not match the journal: "
                + "; ".join(map(str, bad))
                + ". Restore them, or resume with --retake to shoot them again "
                "(nothing was written)"
            )
        if diffs:
            j, _ = Journal.open(jp)
            with j:
                j.append({"type": "note", "forced": True, "differences": diffs})
        retakes: dict[int, set[int]] = {}
        for b in bad:
            retakes.setdefault(b.pose, set()).add(b.frame)
        sim = manifest.simulation.model_dump() if manifest.simulation is not None else None
        request = DeviceRequest(
            d,
            cfg,
            manifest.camera.backend,
            manifest.plan,
            manifest.seed,
            sim,
            (manifest.reference or {}).get("reflectance"),
        )
        with contextlib.ExitStack() as opened:
            dev = _enter(devices, request, opened)
            _check_target_changer([s.model_dump() for s in manifest.schedule], dev, manifest.plan)
            check_calibration_devices(
                manifest.plan, dev.light is not None, dev.target is not None, resumed=True
            )
            for rel, data in dev.files.items():  # sessions made before the devices gave it
                dest = session_file(d, {"file": rel})
                if not dest.exists():
                    write_atomic(dest, data)
            # The schedule's joints were planned for the session's rig; a forced other rig
            # solves each pose anew (its own limits and path rules decide).
            planned = cfg is manifest.rig
            return _run(
                d,
                manifest,
                manifest.plan,
                dev,
                state,
                True,
                retakes,
                subscribers,
                bad,
                planned,
                advisor=advisor,
            )


def _run(
    d: Path,
    manifest: Manifest,
    plan: Plan,
    devices: SessionDevices,
    state: SessionState,
    resumed: bool,
    retake: Mapping[int, set[int]],
    subscribers: Sequence[Subscriber],
    bad: Sequence[BadFrame] = (),
    planned_joints: bool = True,
    advisor: Any = None,
) -> RunResult:
    steps = [s.model_dump() for s in manifest.schedule]
    if not planned_joints:
        for s in steps:
            s["joints"] = None
    jpath = d / JOURNAL
    if jpath.exists():
        journal, _ = Journal.open(jpath)
    else:
        journal = Journal.create(jpath)
    (d / RAW_DIR).mkdir(exist_ok=True)
    for stale in (d / RAW_DIR).glob(".*.tmp"):  # temp files of a write cut by a crash
        stale.unlink()
    counts = {"shots": 0}
    skipped: list[SkippedPose] = []
    retaken: list[str] = []
    closed = set(state.done)

    n_round_steps = [len(adaptive_steps(state.records))]
    stops = [r for r in state.records if r.get("type") == ROUND and r.get("stop") is not None]

    def tally(doc: dict[str, Any]) -> None:
        t = doc.get("type")
        if t == ROUND:
            n_round_steps[0] += len(doc.get("steps") or [])
            if doc.get("stop") is not None:
                stops.append(doc)
        if t == "shot":
            counts["shots"] += 1
            if doc.get("retake"):
                retaken.append(doc["file"])
        if t in ("pose_done", "pose_skipped"):
            closed.add(doc["pose"])
        if t == "pose_skipped":
            skipped.append(SkippedPose(doc["pose"], doc["reason"], doc.get("code")))

    if devices.kinematics is None:
        raise SessionError(
            "SessionDevices.kinematics is missing: a session journals the directions the "
            "rig reached, which takes its forward kinematics"
        )
    engine = Engine(devices, d, [journal.append, tally, *subscribers])
    if plan.adaptive is not None:
        gen = adaptive_session_plan(
            steps,
            plan,
            state.plan_state(retake),
            devices.kinematics.forward,
            devices.noise_floor_dn(plan.bracket.camera_iso()),
            session_dir=d,
            records=state.records,
            pool=read_pool(d),
            advisor=_advisor_for(advisor, plan),
            kinematics=devices.kinematics,
            start_joints=manifest.rig.park_rad,
            skipped={int(r["pose"]) for r in state.skipped},
        )
    else:
        gen = session_plan(
            steps,
            plan,
            state.plan_state(retake),
            devices.kinematics.forward,
            devices.noise_floor_dn(plan.bracket.camera_iso()),
        )
    start = {
        "type": "start",
        "resumed": resumed,
        "software_version": __version__,
        # an adaptive session's journaled rounds are poses of it too (resume: "done"
        # counts theirs, so without them a progress bar read 8 of 5)
        "poses": len(steps) + n_round_steps[0],
        "done": len(state.done),
        "shots": state.n_shots,
    }
    try:
        outcome = run_plan(engine, gen, start)
    finally:
        journal.close()
    result = RunResult(
        d,
        outcome.status,
        len(steps) + n_round_steps[0],
        len(closed),
        counts["shots"],
        skipped,
        retaken,
        outcome.finalizer,
        {k: stops[-1].get(k) for k in ("round", "stop", "poses_done")} if stops else None,
    )
    fin, error = outcome.finalizer, outcome.error
    if outcome.status == "fault":
        where = "camera" if isinstance(error, CameraError) else "rig"
        safe = "parked with torque off" if fin["parked"] else "torque off (not parked)"
        if not fin["torque_off"]:
            safe = "NOT confirmed torque off: check the rig"
        raise SessionStopped(
            f"session {d} stopped on a {where} fault: {error}. The rig is {safe} and the fault "
            f"is in the journal; fix the cause and run 'gonio capture resume {d}'",
            result,
        ) from error
    if outcome.status == "interrupted":
        safe = "torque is off" if fin["torque_off"] else "torque off NOT confirmed: check the rig"
        raise SessionStopped(
            f"session {d} interrupted ({error}); {safe}. Continue with 'gonio capture resume {d}'",
            result,
        )
    return result


def _check_advisor(plan: Plan, advisor: Any) -> None:
    if plan.adaptive is not None and advisor is None:
        raise SessionError(
            f"plan {plan.name!r} is [adaptive]: its rounds need an advisor (the composition "
            "root's gonio.app.adaptive_advisor.FitAdvisor; gonio capture run/resume wire it) "
            "(nothing was moved or written)"
        )


def _advisor_for(advisor: Any, plan: Plan) -> Any:
    """An advisor, or what makes one: ``advisor(plan)`` (a class such as FitAdvisor, or a
    factory)."""
    if isinstance(advisor, type) or not hasattr(advisor, "advise"):
        return advisor(plan)
    return advisor


def _pool_file(dry: DryRun) -> dict[str, bytes]:
    """An adaptive plan's candidate pool, as the session stores it."""
    import json

    pool = dry.schedule.pool
    if pool is None:
        return {}
    return {POOL_FILE: json.dumps(pool.to_json(), separators=(",", ":")).encode()}


def _diff_keys(a: dict, b: dict, prefix: str = "") -> str:
    out = []
    for k in sorted(set(a) | set(b)):
        va, vb = a.get(k), b.get(k)
        if isinstance(va, dict) and isinstance(vb, dict):
            sub = _diff_keys(va, vb, f"{prefix}{k}.")
            if sub:
                out.append(sub)
        elif va != vb:
            out.append(f"{prefix}{k}")
    return ", ".join(out)
