"""The capture session as a plan: a generator of :mod:`gonio.capture.messages`.

One step per pose of the schedule: (target swap), move, settle, read back, then the
bracket -- an adaptive one decides each next exposure from the frame the engine sends
back -- and a checkpoint (``pose_done``).  A pose the rig refuses before moving
(:class:`~gonio.errors.PoseRefused`, thrown into the generator by the engine) is closed
with ``pose_skipped``; every other error propagates to the engine, which journals the
fault and runs the finalizer.

The same generator serves the run, the resume (``state`` holds what the journal already
has: done poses are passed over, a pose cut short continues its bracket, frames listed in
``retake`` are shot again) and the dry run (the engine answers :class:`Shoot` with None:
nothing to judge, the bracket of that pose ends).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Generator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from gonio.capture.bracket import FrameVerdict, judge, next_exposure, predict_exposure, roi_pixels
from gonio.capture.messages import (
    Captured,
    Checkpoint,
    Emit,
    Move,
    Read,
    SetLight,
    SetTarget,
    Settle,
    Shoot,
)
from gonio.capture.plan import Plan
from gonio.devices import RigState
from gonio.errors import CameraError, GonioError, PoseRefused

__all__ = ["RAW_DIR", "PlanState", "PoseSteps", "session_plan"]

RAW_DIR = "raw"

#: ``forward(joints)`` or ``forward(joints, approach)`` (``Kinematics.forward``).
Forward = Callable[..., tuple[Any, Any]]


@dataclass
class PlanState:
    """What the journal already holds, as the plan needs it.

    Attributes
    ----------
    done
        Steps closed by ``pose_done`` or ``pose_skipped``.
    shots
        Step -> its frames' newest ``shot`` records, in frame order.
    retake
        Step -> frames to shoot again (their files failed verification).
    used_exposures
        Requested exposure times (s) of the sample and reference frames already shot
        (dark frames are taken at these).
    records_per_frame
        (step, frame) -> how many ``shot`` records name it (names a retake's file).
    """

    done: set[int] = field(default_factory=set)
    shots: dict[int, list[dict[str, Any]]] = field(default_factory=dict)
    retake: dict[int, set[int]] = field(default_factory=dict)
    used_exposures: set[float] = field(default_factory=set)
    records_per_frame: dict[tuple[int, int], int] = field(default_factory=dict)


def _stem(step: int, frame: int, kind: str, n_before: int = 0) -> str:
    retake = f".r{n_before}" if n_before else ""
    return f"{RAW_DIR}/p{step:04d}_f{frame:02d}_{kind}{retake}"


def _verdict_of(rec: Mapping[str, Any]) -> FrameVerdict | None:
    v = rec.get("bracket")
    if not v:
        return None
    return FrameVerdict(
        float(rec["exposure_time_requested"]),
        bool(v["saturated"]),
        bool(v["underexposed"]),
        float(v["signal_fraction"]),
    )


def _verdicts(shots: Sequence[Mapping[str, Any]]) -> list[FrameVerdict]:
    return [v for v in map(_verdict_of, shots) if v is not None]


def _finite(x: float | None) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def _first_exposure(plan: Plan, prev_verdicts, prev_cos, cos_i: float) -> float:
    if plan.bracket.policy == "fixed":
        return float(plan.bracket.exposures_s[0])
    return predict_exposure(plan.bracket, prev_verdicts, prev_cos, cos_i)


def _continue_exposure(plan: Plan, verdicts, done_shots) -> float | None:
    if plan.bracket.policy == "fixed":
        n = len(done_shots)
        return float(plan.bracket.exposures_s[n]) if n < len(plan.bracket.exposures_s) else None
    return next_exposure(verdicts, plan.bracket)


def judge_shot(plan: Plan, data: bytes, t: float, read_noise_dn: float) -> FrameVerdict:
    """Decode a frame and classify its ROI (the adaptive bracket's decision input)."""
    from gonio.capture.raw import read_raw, roi_exposure_stats

    try:
        frame = read_raw(data, name="captured frame")
    except GonioError as exc:
        raise CameraError(f"camera delivered a frame that cannot be decoded: {exc}") from exc
    stats = roi_exposure_stats(frame, roi_pixels(frame.shape, plan.bracket.roi))
    return judge(stats, t, plan.bracket, read_noise_dn)


def _shot_record(
    step: int, frame: int, kind: str, cap: Captured, t_requested: float
) -> dict[str, Any]:
    shot = cap.shot
    rec: dict[str, Any] = {
        "type": "shot",
        "pose": step,
        "frame": frame,
        "kind": kind,
        "exposure_time": _finite(shot.exposure_time),
        "exposure_time_requested": float(t_requested),
        "iso": _finite(shot.iso),
        "f_number": _finite(shot.f_number),
        "file": cap.file,
        "sha256": cap.sha256,
        "xxh3_128": cap.xxh3_128,
        "bytes": cap.bytes,
    }
    if cap.rig_time is not None:
        rec["rig_time"] = cap.rig_time
    if shot.extra:
        rec["camera"] = {
            k: v for k, v in shot.extra.items() if isinstance(v, str | int | float | bool)
        }
    return rec


def _pose_fields(step: Mapping[str, Any], state: RigState, forward: Forward) -> dict[str, Any]:
    if step["kind"] in ("dark", "flat"):
        wi = wo = wi_a = wo_a = None
    else:
        wi, wo = list(step["wi"]), list(step["wo"])
        # An as-built rig's directions depend on the side of the backlash each joint is
        # on (other kinematics, e.g. tests' stand-ins, need not take the approach).
        asbuilt = not getattr(getattr(forward, "__self__", None), "nominal", True)
        if asbuilt and state.approach:
            a_i, a_o = forward(state.joints, state.approach)
        else:
            a_i, a_o = forward(state.joints)
        wi_a, wo_a = [float(x) for x in a_i], [float(x) for x in a_o]
    return {
        "wi_requested": wi,
        "wo_requested": wo,
        "wi_achieved": wi_a,
        "wo_achieved": wo_a,
        "joints": dict(state.joints),
        "approach": {j: int(v) for j, v in state.approach.items()},
        "temperatures": dict(state.temperatures),
    }


def _retake_fields(old: Mapping[str, Any]) -> dict[str, Any]:
    replaced = {k: old[k] for k in ("file", "xxh3_128", "sha256", "bytes") if k in old}
    return {"retake": True, "replaces": replaced}


def session_plan(
    steps: Sequence[Mapping[str, Any]],
    plan: Plan,
    state: PlanState,
    forward: Forward,
    read_noise_dn: float,
    *,
    first_step: int = 0,
) -> Generator[Any, Any, None]:
    """The messages of a session (see the module docstring).

    Parameters
    ----------
    steps
        The schedule (``manifest.json``'s ``schedule``): ``kind``, ``wi``, ``wo``,
        ``joints`` per step.
    plan
        The validated plan (bracket policy, darks, settle time, ...).
    state
        What the journal already holds (:class:`PlanState`; empty for a new session).
    forward
        ``Kinematics.forward``: achieved directions from read-back joints.
    read_noise_dn
        The camera's noise floor for the bracket decisions, DN rms.
    first_step
        Journal number of ``steps[0]``.
    """
    poses = PoseSteps(plan, state, forward, read_noise_dn)
    for k, step in enumerate(steps, first_step):
        yield from poses.step(k, step)


class PoseSteps:
    """The per-step machinery of a session plan: one step's messages at a time, with
    what carries from step to step (the previous pose's bracket, the target in place,
    the exposures used).  :func:`session_plan` runs a schedule through it; an adaptive
    plan (:mod:`gonio.capture.adaptive`) runs its rounds' steps through the same one."""

    def __init__(
        self, plan: Plan, state: PlanState, forward: Forward, read_noise_dn: float
    ) -> None:
        self.plan, self.state, self.forward = plan, state, forward
        self.read_noise_dn = read_noise_dn
        self.prev_verdicts: list[FrameVerdict] | None = None
        self.prev_cos: float | None = None
        self.target = "sample"
        self.used = set(state.used_exposures)
        self.iso, self.f_number = plan.bracket.camera_iso(), plan.bracket.camera_f_number()
        self.adaptive = plan.bracket.policy == "adaptive"
        #: Steps this run closed as skipped (the rig refused them).
        self.skipped: set[int] = set()

    def step(self, k: int, step: Mapping[str, Any]) -> Generator[Any, Any, None]:
        """The messages of step ``k`` (journal number) of the schedule."""
        plan, state, forward = self.plan, self.state, self.forward
        read_noise_dn = self.read_noise_dn
        iso, f_number, adaptive = self.iso, self.f_number, self.adaptive
        kind = step["kind"]
        done_shots = list(state.shots.get(k, []))
        retake = sorted(state.retake.get(k, ()))
        if k in state.done and not retake:
            if kind not in ("dark", "flat"):
                self.prev_verdicts = _verdicts(done_shots)
                self.prev_cos = float(step["wi"][2])
            return
        if kind == "dark":
            yield from _darks(k, plan, state, done_shots, retake, sorted(self.used), iso, f_number)
            if k not in state.done:
                yield Checkpoint({"type": "pose_done", "pose": k})
            return
        if kind == "flat":
            yield SetTarget("flat")
            yield from _flats(k, plan, state, done_shots, retake, f_number)
            # the sample back in place (the next step swaps again if it needs to)
            yield SetTarget("sample")
            self.target = "sample"
            if k not in state.done:
                yield Checkpoint({"type": "pose_done", "pose": k})
            return
        if kind != self.target:
            yield SetTarget(kind)
            self.target = kind
        wi, wo = tuple(step["wi"]), tuple(step["wo"])
        try:
            yield Move(k, wi, wo, step.get("joints"))
        except PoseRefused as exc:
            # Checked and refused before anything moved: the pose is closed as skipped
            # (inspect lists it) and the session goes on.
            self.skipped.add(k)
            yield Checkpoint(
                {"type": "pose_skipped", "pose": k, "reason": str(exc), "code": exc.reason.value}
            )
            return
        if plan.settle_s > 0:
            yield Settle(plan.settle_s)
        rig_state: RigState = yield Read()
        fields = _pose_fields(step, rig_state, forward)

        # Frames whose files failed verification, shot again at their exposure.
        for frame in retake:
            old = done_shots[frame]
            t = float(old["exposure_time_requested"])
            n = state.records_per_frame.get((k, frame), 1)
            cap = yield Shoot(k, frame, t, iso, f_number, _stem(k, frame, kind, n))
            if cap is None:
                continue
            rec = _shot_record(k, frame, kind, cap, t)
            rec.update(fields)
            if adaptive:
                rec["bracket"] = judge_shot(plan, cap.shot.data, t, read_noise_dn).to_json()
            rec.update(_retake_fields(old))
            yield Emit(rec)
            done_shots[frame] = rec
        if k in state.done:
            self.prev_verdicts, self.prev_cos = _verdicts(done_shots), float(wi[2])
            return

        verdicts = _verdicts(done_shots)
        frame = len(done_shots)
        if frame == 0:
            t = _first_exposure(plan, self.prev_verdicts, self.prev_cos, float(wi[2]))
        else:
            t = _continue_exposure(plan, verdicts, done_shots)
        while t is not None:
            cap = yield Shoot(k, frame, t, iso, f_number, _stem(k, frame, kind))
            if cap is None:  # dry run: nothing to judge, the bracket ends here
                break
            verdict = judge_shot(plan, cap.shot.data, t, read_noise_dn) if adaptive else None
            rec = _shot_record(k, frame, kind, cap, t)
            rec.update(fields)
            if verdict is not None:
                rec["bracket"] = verdict.to_json()
                verdicts.append(verdict)
            yield Emit(rec)
            done_shots.append(rec)
            self.used.add(t)
            frame += 1
            t = _continue_exposure(plan, verdicts, done_shots)
        yield Checkpoint({"type": "pose_done", "pose": k, "frames": frame})
        self.prev_verdicts, self.prev_cos = verdicts, float(wi[2])


def _flats(k, plan, state, done_shots, retake, f_number):
    """The flat-field frames: ``flats.count`` at ``flats.exposure_s`` and the flats' ISO
    (the rig stays where it is: the panel covers the lens)."""
    t, iso = float(plan.flats.exposure_s), plan.flats_iso
    rig_state = yield Read()
    fields = _pose_fields({"kind": "flat"}, rig_state, lambda j: (None, None))
    for frame in retake:
        old = done_shots[frame]
        n = state.records_per_frame.get((k, frame), 1)
        cap = yield Shoot(k, frame, t, iso, f_number, _stem(k, frame, "flat", n))
        if cap is not None:
            rec = _shot_record(k, frame, "flat", cap, t)
            rec.update(fields)
            rec.update(_retake_fields(old))
            yield Emit(rec)
    if k not in state.done:
        for frame in range(len(done_shots), plan.flats.count):
            cap = yield Shoot(k, frame, t, iso, f_number, _stem(k, frame, "flat"))
            if cap is None:
                break
            rec = _shot_record(k, frame, "flat", cap, t)
            rec.update(fields)
            yield Emit(rec)


def _dark_wanted(plan: Plan, exposures, iso) -> list[tuple[float, float | None]]:
    """(exposure time, ISO) of every dark frame: ``darks.count`` per exposure time of the
    plan's list (else every one used), and per flat exposure when the plan has flats."""
    times = list(plan.darks.exposure_times_s) or list(exposures) or list(plan.bracket.exposures_s)
    if not times:
        times = [plan.bracket.exposure_time_s]
    wanted = [(t, iso) for t in sorted(set(times)) for _ in range(plan.darks.count)]
    if plan.flats.count:
        flat = (float(plan.flats.exposure_s), plan.flats_iso)
        if flat not in set(wanted):
            wanted += [flat] * plan.darks.count
    return wanted


def _darks(k, plan, state, done_shots, retake, exposures, iso, f_number):
    wanted = _dark_wanted(plan, exposures, iso)
    rig_state = yield Read()
    fields = _pose_fields({"kind": "dark"}, rig_state, lambda j: (None, None))
    yield SetLight(False)
    for frame in retake:
        old = done_shots[frame]
        t = float(old["exposure_time_requested"])
        n = state.records_per_frame.get((k, frame), 1)
        # the flats' darks at the flats' ISO
        t_iso = wanted[frame][1] if frame < len(wanted) and wanted[frame][0] == t else iso
        cap = yield Shoot(k, frame, t, t_iso, f_number, _stem(k, frame, "dark", n))
        if cap is not None:
            rec = _shot_record(k, frame, "dark", cap, t)
            rec.update(fields)
            rec.update(_retake_fields(old))
            yield Emit(rec)
    if k not in state.done:
        for frame in range(len(done_shots), len(wanted)):
            t, t_iso = wanted[frame]
            cap = yield Shoot(k, frame, t, t_iso, f_number, _stem(k, frame, "dark"))
            if cap is None:
                break
            rec = _shot_record(k, frame, "dark", cap, t)
            rec.update(fields)
            yield Emit(rec)
    yield SetLight(True)
