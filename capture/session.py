"""Capture sessions: plan, run and resume a measurement, crash-safe.

A session is a directory (layout in DEVELOPING.md)::

    SESSION/manifest.json   what was planned with what (written once, atomically)
    SESSION/journal.jsonl   append-only record of what was done (fsync per record)
    SESSION/raw/            the RAW files, written atomically before they are journaled

The run is a plan of steps in the bluesky manner: one step per pose (move, read back,
shoot an adaptive bracket), a checkpoint after each step (the ``pose_done`` record), and a
finalizer that always parks the arms and turns torque off -- after completion, a rig
fault, a camera that went away, Ctrl-C or SIGTERM.  Only SIGKILL or a power cut skip the
finalizer, and then the journal is still consistent: every ``shot`` record points at a
complete file with that sha256, because the file was renamed into place and fsync-ed
before its record was written.

Resume replays the journal: poses with ``pose_done`` are skipped; a pose cut short keeps
the frames it journaled, the rig moves there again and the bracket continues where it
stopped (its decisions are journaled with each frame, so the continuation is the same);
a file written but never journaled is an orphan that the redo overwrites.  So a session
killed at any point and resumed ends with exactly the planned shots, each once.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import math
import os
import signal
import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from gonio import __version__
from gonio.capture.bracket import FrameVerdict, judge, next_exposure, predict_exposure, roi_pixels
from gonio.capture.camera import Camera, CameraInfo, LightSwitch, TargetChanger
from gonio.capture.journal import (
    Journal,
    fsync_dir,
    read_journal,
    sha256_bytes,
    write_atomic,
    xxh3_bytes,
)
from gonio.capture.ordering import move_time_matrix, order_poses, tour_time
from gonio.capture.plan import ExpandedPlan, Plan, Pose, expand_plan, plan_digest, plan_from_dict
from gonio.errors import CameraError, GonioError, RigError, RigFault, SessionError

__all__ = [
    "MANIFEST",
    "JOURNAL",
    "RAW_DIR",
    "SCHEMA_VERSION",
    "RigDevice",
    "Schedule",
    "SessionState",
    "build_schedule",
    "create_session",
    "load_manifest",
    "run_steps",
    "session_state",
]

SCHEMA_VERSION = 1
MANIFEST = "manifest.json"
JOURNAL = "journal.jsonl"
RAW_DIR = "raw"


class RigDevice(Protocol):
    """What the session needs from the rig (``gonio.rig`` device or an adapter)."""

    def move_to(self, wi: np.ndarray, wo: np.ndarray) -> Any: ...

    def read_state(self) -> tuple[dict[str, float], dict[str, float]]:
        """Read-back joint angles (rad) and servo temperatures (degC), by joint."""
        ...

    def read_joints(self) -> dict[str, float]: ...

    def park(self) -> Any: ...

    def torque_off(self) -> Any: ...


# --------------------------------------------------------------------------------------
# Schedule: the ordered steps of a session


@dataclass
class Schedule:
    """The ordered steps of a session and its estimated duration.

    ``steps[k]`` is journaled as pose ``k``: a dict with ``kind`` (``"sample"``,
    ``"reference"`` or ``"dark"``), ``wi``/``wo`` (None for darks), angles in degrees and
    the planned ``joints``.
    """

    steps: list[dict[str, Any]]
    expanded: ExpandedPlan
    travel_time_s: float
    raster_travel_time_s: float
    estimated_duration_s: float
    notes: list[str] = field(default_factory=list)


def _expected_frames(plan: Plan) -> float:
    b = plan.bracket
    return float(len(b.exposures_s)) if b.policy == "fixed" else min(2.0, b.max_frames)


def build_schedule(plan: Plan, kinematics: Any, start_joints: dict[str, float]) -> Schedule:
    """Expand, check against the rig, and order a plan.

    Parameters
    ----------
    plan
        The validated plan.
    kinematics
        ``gonio.rig.kinematics.Kinematics`` of the rig (``check``, ``inverse``,
        ``move_time``).
    start_joints
        Where the rig starts (its park pose), joint name -> rad.

    Raises
    ------
    SessionError
        When no pose of the plan is reachable (the message lists the commonest reasons).
    """
    expanded = expand_plan(plan, rig_check=lambda wi, wo: kinematics.check(wi, wo))
    if not any(p.kind == "sample" for p in expanded.poses):
        reasons: dict[str, int] = {}
        for e in expanded.excluded:
            key = e.reason.split(":")[0]
            reasons[key] = reasons.get(key, 0) + 1
        top = ", ".join(f"{n} x {r}" for r, n in sorted(reasons.items(), key=lambda x: -x[1])[:4])
        raise SessionError(
            f"plan {plan.name!r}: no reachable pose: all {expanded.n_grid} grid poses are "
            f"excluded or reduced ({top or 'empty grid'}); check the grid and exclusions"
        )
    joints = [kinematics.inverse(np.array(p.wi), np.array(p.wo)) for p in expanded.poses]
    servos = getattr(getattr(kinematics, "config", None), "servos", None)
    D = move_time_matrix(joints, kinematics.move_time, start=start_joints, servos=servos)
    # Reference poses are shot as a group at the start or end; order each group apart so
    # the reference target is swapped in only once.
    idx_sample = [k for k, p in enumerate(expanded.poses) if p.kind == "sample"]
    idx_ref = [k for k, p in enumerate(expanded.poses) if p.kind == "reference"]

    def ordered(idx: list[int], start_node: int) -> list[int]:
        if not idx:
            return []
        nodes = [start_node] + [k + 1 for k in idx]
        sub = D[np.ix_(nodes, nodes)]
        tour = order_poses(sub, start=0)
        return [nodes[t] - 1 for t in tour[1:]]

    order_s = ordered(idx_sample, 0)
    if plan.reference.when == "start":
        order_r = ordered(idx_ref, 0)
        order = order_r + ordered(idx_sample, (order_r[-1] + 1) if order_r else 0)
    else:
        order = order_s + ordered(idx_ref, (order_s[-1] + 1) if order_s else 0)
    travel = tour_time(D, [0] + [k + 1 for k in order])
    raster = tour_time(D, [0] + [k + 1 for k in range(len(expanded.poses))])
    steps: list[dict[str, Any]] = []
    for k in order:
        p: Pose = expanded.poses[k]
        d = p.to_json()
        d["joints"] = {j: float(v) for j, v in joints[k].items()}
        steps.append(d)
    if plan.darks.count:
        dark = {"kind": "dark", "wi": None, "wo": None}
        steps.insert(0, dark) if plan.darks.when == "start" else steps.append(dark)
    b = plan.bracket
    per_frame = (
        b.exposures_s and float(np.mean(b.exposures_s)) or b.exposure_time_s
    ) + b.shot_overhead_s
    n_pose = len(expanded.poses)
    est = travel + n_pose * (plan.settle_s + _expected_frames(plan) * per_frame)
    if plan.darks.count:
        n_t = len(plan.darks.exposure_times_s) or (len(b.exposures_s) or 3)
        est += plan.darks.count * n_t * per_frame
    return Schedule(steps, expanded, travel, raster, est)


# --------------------------------------------------------------------------------------
# Session directory


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def load_manifest(session_dir: str | os.PathLike) -> dict[str, Any]:
    """Read ``manifest.json`` of a session.

    Raises
    ------
    SessionError
        When the directory is not a session or the manifest is unreadable.
    """
    path = Path(session_dir) / MANIFEST
    if not path.is_file():
        raise SessionError(f"{session_dir}: not a session directory (no {MANIFEST})")
    try:
        m = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise SessionError(f"{path}: cannot read the manifest: {exc}") from None
    if m.get("schema_version") != SCHEMA_VERSION:
        raise SessionError(
            f"{path}: schema_version {m.get('schema_version')!r}, this gonio reads {SCHEMA_VERSION}"
        )
    return m


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


def create_session(
    session_dir: str | os.PathLike,
    plan: Plan,
    rig_config: Any,
    schedule: Schedule,
    camera_info: CameraInfo,
    simulation: dict[str, Any] | None = None,
) -> Path:
    """Create a session directory: ``raw/``, the manifest, and the journal's start record.

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
        import shutil

        shutil.rmtree(tmp)
    tmp.mkdir()
    (tmp / RAW_DIR).mkdir()
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
        "simulation": simulation,
        "schedule": schedule.steps,
        "excluded": [{**e.pose.to_json(), "reason": e.reason} for e in schedule.expanded.excluded],
        "estimated_duration_s": schedule.estimated_duration_s,
        "travel_time_s": schedule.travel_time_s,
    }
    write_atomic(tmp / MANIFEST, json.dumps(manifest, indent=1).encode())
    fsync_dir(tmp)
    if d.exists():
        d.rmdir()  # empty (checked above); rename cannot replace it on every platform
    os.rename(tmp, d)
    fsync_dir(d.parent)
    return d


# --------------------------------------------------------------------------------------
# State of a session from its journal


@dataclass
class SessionState:
    """What the journal says: done poses, shots per pose, faults, last stop."""

    records: list[dict[str, Any]]
    done: set[int]
    shots: dict[int, list[dict[str, Any]]]
    faults: list[dict[str, Any]]
    last_stop: dict[str, Any] | None
    skipped: list[dict[str, Any]] = field(default_factory=list)

    @property
    def n_shots(self) -> int:
        return sum(len(v) for v in self.shots.values())


def session_state(records: Sequence[dict[str, Any]]) -> SessionState:
    """Summarise journal records (see :func:`gonio.capture.journal.read_journal`)."""
    done: set[int] = set()
    shots: dict[int, list[dict[str, Any]]] = {}
    faults = []
    skipped: list[dict[str, Any]] = []
    last_stop = None
    for r in records:
        t = r.get("type")
        if t == "shot":
            shots.setdefault(int(r["pose"]), []).append(r)
        elif t in ("pose_done", "pose_skipped"):
            done.add(int(r["pose"]))
            if t == "pose_skipped":
                skipped.append(r)
        elif t == "fault":
            faults.append(r)
        elif t == "stop":
            last_stop = r
    return SessionState(list(records), done, shots, faults, last_stop, skipped)


# --------------------------------------------------------------------------------------
# Running


class Interrupted(Exception):
    """SIGTERM/SIGINT arrived: stop after the finalizer."""


@contextlib.contextmanager
def _terminate_as_interrupt() -> Iterator[None]:
    """Turn SIGTERM into an exception in the main thread, so the finalizer runs."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):  # noqa: ARG001
        raise Interrupted(f"signal {signal.Signals(signum).name}")

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def shot_seed(seed: int, pose: int, frame: int) -> int:
    """Per-shot seed for simulated cameras: a session is reproducible from its seed, and a
    redone shot renders the same noise."""
    return int(np.random.SeedSequence([int(seed), int(pose), int(frame)]).generate_state(1)[0])


def _file_name(pose: int, frame: int, kind: str, suffix: str) -> str:
    return f"{RAW_DIR}/p{pose:04d}_f{frame:02d}_{kind}{suffix}"


def _verdict_of(rec: dict[str, Any]) -> FrameVerdict | None:
    v = rec.get("bracket")
    if not v:
        return None
    return FrameVerdict(
        float(rec["exposure_time_requested"]),
        bool(v["saturated"]),
        bool(v["underexposed"]),
        float(v["signal_fraction"]),
    )


def _fault_record(exc: BaseException, source: str) -> dict[str, Any]:
    rec: dict[str, Any] = {"type": "fault", "source": source, "error": str(exc)}
    for attr in ("servo", "servo_id", "error_bits", "hardware_error", "register", "joint"):
        v = getattr(exc, attr, None)
        if v is not None:
            rec["servo" if attr == "servo_id" else attr] = (
                v if isinstance(v, int | str | float) else str(v)
            )
    return rec


EventHook = Callable[[dict[str, Any]], None]


def run_steps(
    session_dir: str | os.PathLike,
    rig: RigDevice,
    camera: Camera,
    kinematics: Any,
    *,
    on_event: EventHook | None = None,
    resumed: bool = False,
    read_noise_dn: float = 2.0,
) -> str:
    """Run (or continue) a session's steps with the finalizer; returns the stop status.

    Parameters
    ----------
    session_dir
        A directory made by :func:`create_session`.
    rig, camera
        Open devices.
    kinematics
        The rig's kinematics (forward, to journal the achieved directions).
    on_event
        Called with every record after it is durable (progress bars, tests).
    resumed
        Mark the start record as a resume.
    read_noise_dn
        Noise floor for the bracket decisions (DN rms).

    Returns
    -------
    str
        ``"completed"``, ``"fault"`` or ``"interrupted"``; the journal ends with a
        ``stop`` record carrying it.
    """
    d = Path(session_dir)
    manifest = load_manifest(d)
    plan = plan_from_dict(manifest["plan"], f"{d / MANIFEST}: plan")
    steps: list[dict[str, Any]] = manifest["schedule"]
    jpath = d / JOURNAL
    if jpath.exists():
        journal, records = Journal.open(jpath)
    else:
        journal, records = Journal.create(jpath), []
    (d / RAW_DIR).mkdir(exist_ok=True)
    for stale in (d / RAW_DIR).glob(".*.tmp"):  # temp files of a write cut by a crash
        stale.unlink()
    state = session_state(records)
    _verify_journaled_files(d, state)

    def emit(rec: dict[str, Any]) -> dict[str, Any]:
        out = journal.append(rec)
        if on_event is not None:
            on_event(out)
        return out

    status = "interrupted"
    error: BaseException | None = None
    fin: dict[str, Any] = {"parked": False, "torque_off": False}
    try:
        with _terminate_as_interrupt():
            emit(
                {
                    "type": "start",
                    "resumed": resumed,
                    "software_version": __version__,
                    "poses": len(steps),
                    "done": len(state.done),
                    "shots": state.n_shots,
                }
            )
            try:
                _run_all(d, plan, steps, state, rig, camera, kinematics, emit, read_noise_dn)
                status = "completed"
            except RigFault as exc:
                emit(_fault_record(exc, "rig"))
                status, error = "fault", exc
            except CameraError as exc:
                emit(_fault_record(exc, "camera"))
                status, error = "fault", exc
            except RigError as exc:
                emit(_fault_record(exc, "rig"))
                status, error = "fault", exc
            except (KeyboardInterrupt, Interrupted) as exc:
                status, error = "interrupted", exc
            finally:
                fin = _finalize(rig, camera)
                emit({"type": "stop", "status": status, **fin})
    finally:
        journal.close()
    if error is not None and status == "fault":
        where = "camera" if isinstance(error, CameraError) else "rig"
        safe = "parked with torque off" if fin["parked"] else "torque off (not parked)"
        if not fin["torque_off"]:
            safe = "NOT confirmed torque off: check the rig"
        raise SessionError(
            f"session {d} stopped on a {where} fault: {error}. The rig is {safe} and the fault "
            f"is in the journal; fix the cause and run 'gonio capture resume {d}'"
        ) from error
    if status == "interrupted":
        safe = "torque is off" if fin["torque_off"] else "torque off NOT confirmed: check the rig"
        raise SessionError(
            f"session {d} interrupted ({error}); {safe}. Continue with 'gonio capture resume {d}'"
        )
    return status


def _verify_journaled_files(d: Path, state: SessionState) -> None:
    """Every journaled file must exist with its size (hashes: ``gonio capture inspect``)."""
    for shots in state.shots.values():
        for s in shots:
            p = d / s["file"]
            if not p.is_file():
                raise SessionError(
                    f"{p}: journaled (sha256 {s['sha256'][:12]}...) but missing; the session "
                    "directory was changed by hand; restore the file before resuming"
                )
            if "bytes" in s and p.stat().st_size != s["bytes"]:
                raise SessionError(
                    f"{p}: size {p.stat().st_size} differs from the journal's {s['bytes']}"
                )


def _finalize(rig: RigDevice, camera: Camera) -> dict[str, Any]:
    """Park the arms and turn torque off, whatever happened; report what failed."""
    out: dict[str, Any] = {"parked": False, "torque_off": False}
    errors = []
    if isinstance(camera, LightSwitch):
        with contextlib.suppress(Exception):
            camera.set_light(True)
    if isinstance(camera, TargetChanger):
        with contextlib.suppress(Exception):
            camera.set_target("sample")
    try:
        rig.park()
        out["parked"] = True
    except Exception as exc:  # noqa: BLE001 - the finalizer must reach torque off
        errors.append(f"park: {exc}")
    try:
        unconfirmed = rig.torque_off()
        # The journal must not claim a safe state nobody saw: a silent servo may still
        # hold torque (the broadcast write reached it, or not).
        out["torque_off"] = not unconfirmed
        if unconfirmed:
            out["torque_unconfirmed"] = list(unconfirmed)
            errors.append(f"torque off not confirmed by servo(s) {list(unconfirmed)}")
    except Exception as exc:  # noqa: BLE001
        errors.append(f"torque off: {exc}")
    if errors:
        out["finalizer_errors"] = errors
    return out


def _cos_theta(w: Sequence[float] | None) -> float | None:
    return None if w is None else float(w[2])


def _run_all(d, plan, steps, state, rig, camera, kinematics, emit, read_noise_dn) -> None:
    prev_verdicts: list[FrameVerdict] | None = None
    prev_cos: float | None = None
    target = "sample"
    used_exposures: set[float] = set()
    for r in state.records:
        if r.get("type") == "shot" and r.get("kind") != "dark":
            used_exposures.add(float(r["exposure_time_requested"]))
    for k, step in enumerate(steps):
        kind = step["kind"]
        done_shots = state.shots.get(k, [])
        if k in state.done:
            if kind != "dark":
                prev_verdicts = [v for v in map(_verdict_of, done_shots) if v is not None]
                prev_cos = _cos_theta(step["wi"])
            continue
        if kind == "dark":
            _shoot_darks(d, plan, k, done_shots, sorted(used_exposures), rig, camera, emit)
            emit({"type": "pose_done", "pose": k})
            continue
        if kind != target and isinstance(camera, TargetChanger):
            camera.set_target(kind)
            target = kind
        wi, wo = np.array(step["wi"]), np.array(step["wo"])
        before = rig.read_joints()  # a RigError here is the bus failing: a fault
        try:
            rig.move_to(wi, wo)
        except RigFault:
            raise
        except RigError as exc:
            # Refused before anything moved (e.g. no collision-free path from here): the
            # pose is recorded as failed and the session goes on; 'inspect' lists it.
            # But the rig's transport raises RigError too (a servo that did not answer,
            # before or during the move): journaling that as a skip lost every remaining
            # pose for good (resume never retries a skipped pose), so only a rig that
            # still answers, in the pose it had, counts as having refused.
            if not _refused_in_place(rig, before):
                raise
            emit({"type": "pose_skipped", "pose": k, "reason": str(exc)})
            continue
        joints, temps = rig.read_state()
        wi_a, wo_a = kinematics.forward(joints)
        verdicts = [v for v in map(_verdict_of, done_shots) if v is not None]
        frame = len(done_shots)
        if frame == 0:
            t = _first_exposure(plan, prev_verdicts, prev_cos, float(wi[2]))
        else:
            t = _continue_exposure(plan, verdicts, done_shots)
        while t is not None:
            shot = camera.capture(
                t,
                plan.bracket.camera_iso(),
                plan.bracket.camera_f_number(),
                seed=shot_seed(plan.seed, k, frame),
            )
            verdict = (
                _judge_shot(plan, shot, t, read_noise_dn)
                if plan.bracket.policy == "adaptive"
                else None
            )
            rec = _store_shot(d, k, frame, kind, shot, t)
            rec.update(
                wi_requested=list(step["wi"]),
                wo_requested=list(step["wo"]),
                wi_achieved=[float(x) for x in wi_a],
                wo_achieved=[float(x) for x in wo_a],
                joints=joints,
                temperatures=temps,
            )
            if verdict is not None:
                rec["bracket"] = verdict.to_json()
                verdicts.append(verdict)
            emit(rec)
            done_shots = [*done_shots, rec]
            used_exposures.add(t)
            frame += 1
            t = _continue_exposure(plan, verdicts, done_shots)
        emit({"type": "pose_done", "pose": k, "frames": frame})
        prev_verdicts, prev_cos = verdicts, float(wi[2])


#: Read-back joint change (rad) below which a refused move counts as "nothing moved":
#: well above a holding servo's jitter (1-2 pulses, 0.09-0.18 deg), well below any move.
_REFUSAL_TOLERANCE_RAD = math.radians(0.5)


def _refused_in_place(rig: RigDevice, before: dict[str, float]) -> bool:
    """True when the rig still answers and has not left the joints ``before`` (rad)."""
    try:
        after = rig.read_joints()
    except RigError:
        return False
    return all(abs(after.get(j, math.inf) - v) <= _REFUSAL_TOLERANCE_RAD for j, v in before.items())


def _first_exposure(plan, prev_verdicts, prev_cos, cos_i) -> float:
    if plan.bracket.policy == "fixed":
        return float(plan.bracket.exposures_s[0])
    return predict_exposure(plan.bracket, prev_verdicts, prev_cos, cos_i)


def _continue_exposure(plan, verdicts, done_shots) -> float | None:
    if plan.bracket.policy == "fixed":
        n = len(done_shots)
        return float(plan.bracket.exposures_s[n]) if n < len(plan.bracket.exposures_s) else None
    return next_exposure(verdicts, plan.bracket)


def _judge_shot(plan: Plan, shot, t: float, read_noise_dn: float) -> FrameVerdict:
    from gonio.capture.raw import read_raw, roi_exposure_stats

    try:
        frame = read_raw(shot.data, name="captured frame")
    except GonioError as exc:
        raise CameraError(f"camera delivered a frame that cannot be decoded: {exc}") from exc
    stats = roi_exposure_stats(frame, roi_pixels(frame.shape, plan.bracket.roi))
    return judge(stats, t, plan.bracket, read_noise_dn)


def _store_shot(
    d: Path, pose: int, frame: int, kind: str, shot, t_requested: float
) -> dict[str, Any]:
    """Write the file atomically; return its journal record (not yet journaled)."""
    name = _file_name(pose, frame, kind, shot.suffix or ".raw")
    write_atomic(d / name, shot.data)
    rec: dict[str, Any] = {
        "type": "shot",
        "pose": pose,
        "frame": frame,
        "kind": kind,
        "exposure_time": _finite(shot.exposure_time),
        "exposure_time_requested": float(t_requested),
        "iso": _finite(shot.iso),
        "f_number": _finite(shot.f_number),
        "file": name,
        "sha256": sha256_bytes(shot.data),
        "xxh3_128": xxh3_bytes(shot.data),
        "bytes": len(shot.data),
    }
    if shot.extra:
        rec["camera"] = {
            k: v for k, v in shot.extra.items() if isinstance(v, str | int | float | bool)
        }
    return rec


def _finite(x: float) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def _shoot_darks(d, plan, k, done_shots, exposures, rig, camera, emit) -> None:
    if not isinstance(camera, LightSwitch):
        raise CameraError(
            "the plan asks for dark frames (darks.count > 0) but this camera backend cannot "
            "switch the light off; cap the lens and set darks.count = 0, or use a rig light"
        )
    times = list(plan.darks.exposure_times_s) or list(exposures) or list(plan.bracket.exposures_s)
    if not times:
        times = [plan.bracket.exposure_time_s]
    wanted = [t for t in sorted(set(times)) for _ in range(plan.darks.count)]
    joints, temps = rig.read_state()
    camera.set_light(False)
    try:
        for frame in range(len(done_shots), len(wanted)):
            t = wanted[frame]
            shot = camera.capture(
                t,
                plan.bracket.camera_iso(),
                plan.bracket.camera_f_number(),
                seed=shot_seed(plan.seed, k, frame),
            )
            rec = _store_shot(d, k, frame, "dark", shot, t)
            rec.update(
                wi_requested=None,
                wo_requested=None,
                wi_achieved=None,
                wo_achieved=None,
                joints=joints,
                temperatures=temps,
            )
            emit(rec)
    finally:
        camera.set_light(True)


# --------------------------------------------------------------------------------------
# Inspecting


def inspect_session(session_dir: str | os.PathLike, verify: bool = True) -> dict[str, Any]:
    """What a session has done, what failed, what is left (``gonio capture inspect``).

    Parameters
    ----------
    session_dir
        The session directory.
    verify
        Hash every journaled RAW file and compare with its sha256.

    Returns
    -------
    dict
        ``status`` (last stop status, or ``"running or crashed"``), ``poses_total``,
        ``poses_done``, ``partial_poses``, ``shots``, ``faults``, ``bad_files``,
        ``orphans`` (RAW files no record points at), ``files_verified``.
    """
    from gonio.capture.journal import sha256_file

    d = Path(session_dir)
    manifest = load_manifest(d)
    jp = d / JOURNAL
    records = read_journal(jp) if jp.exists() else []
    st = session_state(records)
    bad, verified = [], 0
    journaled = set()
    for shots in st.shots.values():
        for s in shots:
            journaled.add(s["file"])
            p = d / s["file"]
            if not p.is_file():
                bad.append(f"{s['file']}: missing")
            elif verify:
                if sha256_file(p) != s["sha256"]:
                    bad.append(f"{s['file']}: sha256 differs from the journal")
                else:
                    verified += 1
    raw = d / RAW_DIR
    orphans = (
        sorted(
            f"{RAW_DIR}/{p.name}"
            for p in raw.iterdir()
            if p.is_file() and f"{RAW_DIR}/{p.name}" not in journaled
        )
        if raw.is_dir()
        else []
    )
    dup = len(journaled) != st.n_shots
    if dup:
        bad.append("journal names a file more than once")
    status = (
        st.last_stop["status"]
        if st.last_stop
        else ("not started" if not records else "running or crashed")
    )
    if st.last_stop and records and records[-1].get("type") != "stop":
        status = "running or crashed"
    return {
        "plan": manifest["plan"].get("name"),
        "camera": manifest["camera"].get("backend"),
        "status": status,
        "poses_total": len(manifest["schedule"]),
        "poses_done": len(st.done),
        "partial_poses": sorted(set(st.shots) - st.done),
        "shots": st.n_shots,
        "faults": st.faults,
        "skipped": [{"pose": r["pose"], "reason": r["reason"]} for r in st.skipped],
        "bad_files": bad,
        "orphans": orphans,
        "files_verified": verified,
    }


# --------------------------------------------------------------------------------------
# Opening the hardware (or the simulated hardware)

VIRTUAL_PORTS = ("virtual", "sim", "simulated")


@dataclass
class Devices:
    """The open rig, camera and kinematics of a session run."""

    rig: Any
    camera: Any
    kinematics: Any
    bus: Any = None

    def read_noise_dn(self, manifest: dict[str, Any]) -> float:
        """Noise floor for the bracket decisions, DN rms."""
        iso = manifest["plan"]["bracket"]["iso"]
        iso = 100.0 if iso == "camera" else float(iso)
        f = getattr(self.camera, "read_noise_dn", None)
        return float(f(iso)) if callable(f) else 2.0


def is_virtual_port(port: str) -> bool:
    """A rig port that asks for the simulator's virtual bus (``"virtual"``)."""
    return port.strip().lower() in VIRTUAL_PORTS


@contextlib.contextmanager
def open_devices(
    rig_config: Any,
    camera_backend: str,
    *,
    simulation: dict[str, Any] | None = None,
    camera_port: str | None = None,
    seed: int = 0,
    reference_reflectance: float | tuple[float, float, float] | None = None,
) -> Iterator[Devices]:
    """Open the rig (starting a virtual bus for ``bus.port = "virtual"``) and the camera.

    Parameters
    ----------
    rig_config
        ``RigConfig``.
    camera_backend
        ``"simulated"`` or ``"gphoto2"``.
    simulation
        ``{"scene": document or None, "width", "height", "time_scale"}`` for the simulated
        backend and the virtual bus.
    camera_port
        gphoto2 port.
    seed
        Seed of the virtual bus.
    reference_reflectance
        The plan's ``reference.reflectance`` (the session manifest's on resume): the
        simulated camera renders the reference target with this albedo, so that the
        reduction, which reads it from the manifest, calibrates against what was shot.
        Falls back to ``simulation["reference_reflectance"]``, then to the simulated
        camera's default (0.99).

    Everything opened is closed on exit (torque off is the session's finalizer's job and
    is repeated here as a last resort).
    """
    from gonio.capture.camera import open_camera
    from gonio.rig.kinematics import Kinematics

    sim = simulation or {}
    kin = Kinematics(rig_config)
    with contextlib.ExitStack() as stack:
        bus = None
        cfg = rig_config
        if is_virtual_port(rig_config.bus.port):
            from gonio.simulator.servo_model import VirtualServo
            from gonio.simulator.virtual_bus import VirtualBus

            # The virtual rig starts where a real one is left: parked.
            park = rig_config.park_pulses
            servos = [
                VirtualServo(s.id, model=s.model, position=park[s.id]) for s in rig_config.servos
            ]
            bus = VirtualBus(
                servos,
                baud_rate=rig_config.bus.baud_rate,
                seed=seed,
                time_scale=float(sim.get("time_scale") or 1.0),
            )
            stack.enter_context(bus)
            cfg = rig_config.model_copy(
                update={"bus": rig_config.bus.model_copy(update={"port": bus.port})}
            )
        rig = stack.enter_context(open_rig(cfg))
        if camera_backend == "simulated":
            scene = sim.get("scene")
            if isinstance(scene, dict):
                from gonio.simulator.scene import parse_scene

                scene = dict(scene)
                base = scene.pop("_base_dir", None)
                scene = parse_scene(scene, "simulation scene", Path(base) if base else None)
            refl = reference_reflectance
            if refl is None:
                refl = sim.get("reference_reflectance")
            if isinstance(refl, list):
                refl = tuple(float(x) for x in refl)
            camera = open_camera(
                "simulated",
                rig=rig,
                kinematics=kin,
                scene=scene,
                width=sim.get("width"),
                height=sim.get("height"),
                **({"reference_albedo": refl} if refl is not None else {}),
            )
        else:
            camera = open_camera(camera_backend, **({"port": camera_port} if camera_port else {}))
        stack.callback(camera.close)
        yield Devices(rig, camera, kin, bus)


class SessionRig:
    """Adapter from :class:`gonio.rig.device.Rig` to the session's :class:`RigDevice`."""

    def __init__(self, rig: Any) -> None:
        self.rig = rig

    def move_to(self, wi: np.ndarray, wo: np.ndarray) -> Any:
        return self.rig.move_to(wi, wo)

    def read_state(self) -> tuple[dict[str, float], dict[str, float]]:
        states = self.rig.read_states()
        return (
            {j: float(s.position) for j, s in states.items()},
            {j: float(s.temperature) for j, s in states.items()},
        )

    def read_joints(self) -> dict[str, float]:
        return {j: float(v) for j, v in self.rig.joints().items()}

    def park(self) -> Any:
        return self.rig.park()

    def torque_off(self) -> Any:
        return self.rig.torque_off()


@contextlib.contextmanager
def open_rig(config: Any) -> Iterator[SessionRig]:
    """Open the rig of ``config`` (pings, checks models, reboots servos left in a fault)."""
    from gonio.rig.device import Rig

    with Rig(config) as rig:
        yield SessionRig(rig)
