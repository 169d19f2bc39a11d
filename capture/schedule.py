"""The schedule of a session: expansion, visiting order, and the dry run.

:func:`build_schedule` expands a plan against the rig's kinematics, orders the poses for
the least servo travel (:mod:`gonio.capture.ordering`), then *executes the session plan*
(:func:`gonio.capture.session_plan.session_plan`, the very generator a run executes)
against a :class:`DryRunRig`: a rig made of the kinematics alone, which answers each move
with ``Kinematics.inverse(wi, wo, current=<the previous pose's joints>)``, path check from
the previous pose included.  So every refusal a run would meet on a nominal rig shows in
``gonio capture plan``, and each step records the joints the dry run chose, which the run
passes to ``rig.move_to(wi, wo, joints=...)``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from gonio.capture.engine import Engine, SessionDevices
from gonio.capture.messages import Move, Shoot
from gonio.capture.ordering import move_time_matrix, order_poses, tour_time
from gonio.capture.plan import ExpandedPlan, Plan, Pose, expand_plan
from gonio.capture.session_plan import PlanState, session_plan
from gonio.devices import MoveResult, RigState
from gonio.errors import PoseRefused, SessionError
from gonio.radiometry.frames import angle_between

__all__ = [
    "DryRunRig",
    "Refusal",
    "Schedule",
    "StageProgress",
    "build_schedule",
    "dry_run",
    "estimate_duration",
    "with_calibration_steps",
    "with_reference_groups",
]


@dataclass
class Refusal:
    """A step the dry run's kinematics refused: ``code`` (a ``RefusalReason`` value)
    and the sentence."""

    step: int
    code: str
    message: str


@dataclass
class Schedule:
    """The ordered steps of a session and its estimated duration.

    ``steps[k]`` is journaled as pose ``k``: a dict with ``kind`` (``"sample"``,
    ``"reference"``, ``"dark"`` or ``"flat"``), ``wi``/``wo`` (None for darks and
    flats), angles in degrees, the ``joints`` the dry run chose (rad; absent when
    refused) and ``refused`` (``{"code", "message"}``) when the dry run refused the step.
    """

    steps: list[dict[str, Any]]
    expanded: ExpandedPlan
    travel_time_s: float
    raster_travel_time_s: float
    estimated_duration_s: float
    refused: list[Refusal] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    #: An adaptive plan's candidate pool (its steps are the seed design; the rounds'
    #: steps are journaled as they are chosen: :mod:`gonio.capture.adaptive`).
    pool: Any = None


class DryRunRig:
    """A rig of kinematics alone: moves are solved, checked and remembered, not made.

    Implements :class:`gonio.devices.RigDevice`.  ``move_to`` solves from the joints of
    the last move it accepted (the park pose at first), so the path check sees the same
    previous pose as the run; a refused move leaves the joints where they were.  With
    ``joints`` (a joint-pose plan's step) it moves there, checked as the rig checks them.
    It tracks the approach signs as :class:`gonio.rig.device.Rig` does (a move beyond
    the position tolerance sets a joint's sign, a smaller one keeps it; the first move takes up
    the backlash of an unmoved joint from below), so the schedule's joints and
    directions are those of the run.
    """

    def __init__(self, kinematics: Any, start_joints: Mapping[str, float]) -> None:
        self.kinematics = kinematics
        self.joints = {k: float(v) for k, v in start_joints.items()}
        self.approach: dict[str, int] = dict.fromkeys(self.joints, 0)

    def _approach_after(self, q: Mapping[str, float]) -> dict[str, int]:
        config = getattr(self.kinematics, "config", None)
        if config is None:
            return dict(self.approach)
        from gonio.rig.kinematics import approach_of_move

        appr = approach_of_move(config, self.joints, q, self.approach)
        for s in config.servos:  # the rig's pre-move: from below
            if appr[s.joint] == 0 and s.backlash_deg > 0:
                appr[s.joint] = 1
        return appr

    def move_to(
        self, wi: ArrayLike, wo: ArrayLike, *, joints: Mapping[str, float] | None = None
    ) -> MoveResult:
        wi = np.asarray(wi, dtype=np.float64)
        wo = np.asarray(wo, dtype=np.float64)
        # Only an as-built rig's kinematics needs the approach (duck-typed kinematics
        # of other rigs need not take it).
        asbuilt = not getattr(self.kinematics, "nominal", True)
        extra = {"approach": self.approach} if asbuilt else {}
        if joints is None:
            # PoseRefused: nothing moved
            q = self.kinematics.inverse(wi, wo, current=self.joints, **extra)
        else:
            q = {k: float(v) for k, v in joints.items()}
            refusal = self.kinematics.joints_refusal(q) or self.kinematics.path_refusal(
                self.joints, q
            )
            if refusal is not None:
                raise PoseRefused(refusal.reason, f"refusing to move: {refusal}")
        duration = self.kinematics.move_time(self.joints, q)
        self.approach = self._approach_after(q)
        self.joints = {k: float(v) for k, v in q.items()}
        ai, ao = self.kinematics.forward(self.joints, *([self.approach] if asbuilt else []))
        wi_u, wo_u = wi / np.linalg.norm(wi), wo / np.linalg.norm(wo)
        return MoveResult(
            wi=wi_u,
            wo=wo_u,
            wi_achieved=ai,
            wo_achieved=ao,
            joints=dict(self.joints),
            error_i=float(angle_between(ai, wi_u)),
            error_o=float(angle_between(ao, wo_u)),
            duration=float(duration),
        )

    def read(self) -> RigState:
        return RigState(joints=dict(self.joints), approach=dict(self.approach))

    def stop(self) -> None:
        pass

    def park(self) -> dict[str, float]:
        return dict(self.joints)

    def torque_off(self) -> list[int]:
        return []


class _Dark:
    """The dry run's light and target: nothing to switch."""

    def set_light(self, on: bool) -> None:
        pass

    def set_target(self, kind: str) -> None:
        pass


def dry_run(
    steps: list[dict[str, Any]],
    plan: Plan,
    kinematics: Any,
    start_joints: Mapping[str, float],
    approach_out: dict[int, dict[str, int]] | None = None,
    *,
    start_approach: Mapping[str, int] | None = None,
    first_step: int = 0,
) -> tuple[dict[int, dict[str, float]], list[Refusal]]:
    """Execute the session plan against a :class:`DryRunRig`.

    Parameters
    ----------
    approach_out
        When given, filled with step -> the approach signs after its move.
    start_approach
        The joints' approach signs at ``start_joints`` (default: unknown, as after
        connecting).
    first_step
        Journal number of ``steps[0]`` (an adaptive round's batch continues the session).

    Returns
    -------
    joints, refused
        Step -> joints the dry run moved to (rad), and the refused steps.
    """
    rig = DryRunRig(kinematics, start_joints)
    if start_approach is not None:
        rig.approach.update({k: int(v) for k, v in start_approach.items()})
    nothing = _Dark()
    devices = SessionDevices(
        rig,
        camera=None,  # type: ignore[arg-type] - Shoot is answered below, never by a camera
        light=nothing,
        target=nothing,
        kinematics=kinematics,
        sleep=lambda s: None,
    )
    joints: dict[int, dict[str, float]] = {}
    refused: list[Refusal] = []

    def move(msg: Move) -> MoveResult:
        res = rig.move_to(msg.wi, msg.wo, joints=msg.joints)
        joints[msg.step] = dict(res.joints)
        if approach_out is not None:
            approach_out[msg.step] = dict(rig.approach)
        return res

    def watch(doc: dict[str, Any]) -> None:
        if doc.get("type") == "pose_skipped":
            refused.append(Refusal(int(doc["pose"]), str(doc["code"]), str(doc["reason"])))

    engine = Engine(devices, None, [watch], handlers={Move: move, Shoot: lambda msg: None})
    engine.execute(
        session_plan(steps, plan, PlanState(), kinematics.forward, 2.0, first_step=first_step)
    )
    return joints, refused


def _expected_frames(plan: Plan) -> float:
    b = plan.bracket
    return float(len(b.exposures_s)) if b.policy == "fixed" else min(2.0, b.max_frames)


#: ``progress(stage, done, total)`` of a long dry run: stages ``"expand"`` (grid poses),
#: ``"solve"`` (poses solved from home), ``"order"`` and ``"dry run"`` (steps).
StageProgress = Callable[[str, int, int], None]


def build_schedule(
    plan: Plan,
    kinematics: Any,
    start_joints: dict[str, float],
    progress: StageProgress | None = None,
) -> Schedule:
    """Expand, check against the rig, order, and dry-run a plan.

    Parameters
    ----------
    plan
        The validated plan.
    kinematics
        ``gonio.rig.kinematics.Kinematics`` of the rig (``check``, ``inverse``,
        ``move_time``, ``forward``).
    start_joints
        Where the rig starts (its park pose), joint name -> rad.
    progress
        Told how far each stage has come (a large plan takes minutes to dry-run).

    Raises
    ------
    SessionError
        When no pose of the plan is reachable (the message lists the commonest reasons).
    ConfigError
        When the plan exceeds its ``[limits]`` (checked before anything is expanded).
    """

    def tell(stage: str, done: int, total: int) -> None:
        if progress is not None:
            progress(stage, done, total)

    expanded = expand_plan(
        plan,
        rig_check=kinematics.refusal,
        progress=lambda d, t: tell("expand", d, t),
        kinematics=kinematics,
    )
    if not any(p.kind != "reference" for p in expanded.poses):
        by_code: dict[str, list[str]] = {}
        for e in expanded.excluded:
            by_code.setdefault(e.code, []).append(e.reason)
        top = ", ".join(
            f"{len(r)} x {code} (e.g. {r[0]})"
            for code, r in sorted(by_code.items(), key=lambda x: -len(x[1]))[:4]
        )
        raise SessionError(
            f"plan {plan.name!r}: no reachable pose: all {expanded.n_grid} "
            f"{'joint' if plan.is_joint_pose_plan else 'grid'} poses are "
            f"excluded or reduced ({top or 'empty grid'}); check the "
            f"{'joint poses' if plan.is_joint_pose_plan else 'grid and exclusions'}"
        )
    if plan.is_joint_pose_plan:
        return _joint_pose_schedule(plan, expanded, kinematics, start_joints, tell)
    # The visiting order needs a move time between every pair of poses before the path
    # is known, so it uses each pose's solution from home; the dry run below then solves
    # each pose from the one before it, as the run will.
    n = len(expanded.poses)
    home_joints = []
    for k, p in enumerate(expanded.poses):
        if k % 100 == 0:
            tell("solve", k, n)
        home_joints.append(kinematics.inverse(np.array(p.wi), np.array(p.wo)))
    tell("solve", n, n)
    servos = getattr(getattr(kinematics, "config", None), "servos", None)
    tell("order", 0, 1)
    D = move_time_matrix(home_joints, kinematics.move_time, start=start_joints, servos=servos)
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
    raster = tour_time(D, [0] + [k + 1 for k in range(len(expanded.poses))])
    # Repeated reference groups (every_poses) in the samples' order, the group ordered
    # as at ``when``.
    order_ref = [k for k in order if expanded.poses[k].kind == "reference"]
    order = with_reference_groups(
        [k for k in order if expanded.poses[k].kind != "reference"], order_ref, plan
    )
    travel = tour_time(D, [0] + [k + 1 for k in order])
    steps: list[dict[str, Any]] = []
    for k in order:
        p: Pose = expanded.poses[k]
        steps.append(p.to_json())
    # an adaptive plan's calibration steps "at the end" follow its last round
    steps = with_calibration_steps(steps, plan, ends=not plan.is_adaptive)

    tell("order", 1, 1)
    tell("dry run", 0, len(steps))
    joints, refused = dry_run(steps, plan, kinematics, start_joints)
    tell("dry run", len(steps), len(steps))
    for k, step in enumerate(steps):
        if k in joints:
            step["joints"] = joints[k]
    for r in refused:
        steps[r.step]["refused"] = {"code": r.code, "message": r.message}

    est = _estimated_duration(plan, len(expanded.poses), travel)
    if plan.adaptive is not None and plan.adaptive.max_time_s is not None:
        if est > plan.adaptive.max_time_s:
            from gonio.errors import ConfigError

            raise ConfigError(
                f"{plan._source}: plan {plan.name!r}: adaptive.max_time_s = "
                f"{plan.adaptive.max_time_s:g} s is smaller than the seed design's estimated "
                f"{est:.0f} s ({len(expanded.poses)} poses: travel {travel:.0f} s + "
                "exposures and downloads), which is always measured: raise max_time_s or "
                "lower seed_poses (nothing was moved)"
            )
    return Schedule(steps, expanded, travel, raster, est, refused, pool=expanded.pool)


def with_reference_groups(samples: list[Any], group: list[Any], plan: Plan) -> list[Any]:
    """The visiting order with the reference ``group`` at ``plan.reference.when`` and
    again after every ``plan.reference.every_poses``-th sample (never twice in a row).

    ``samples`` and ``group`` are steps (or pose indices) in their own orders; the
    result holds ``plan.reference_repeats(len(samples))`` copies of the group.
    """
    if not group:
        return list(samples)
    n = plan.reference.every_poses
    start = plan.reference.when == "start"
    out: list[Any] = list(group) if start else []
    for i, s in enumerate(samples, 1):
        out.append(s)
        if n and i % n == 0:
            out.extend(group)
    if not start and not (n and samples and len(samples) % n == 0):
        out.extend(group)
    return out


def with_calibration_steps(
    steps: list[dict[str, Any]], plan: Plan, *, starts: bool = True, ends: bool = True
) -> list[dict[str, Any]]:
    """``steps`` with the flat-field step and the dark step at their ``when``: at the
    start darks first, at the end darks last (the light is off for the least time
    between the light-on frames).  ``starts``/``ends``: add those at that end only."""
    steps = list(steps)
    if plan.flats.count:
        flat = {"kind": "flat", "wi": None, "wo": None}
        if plan.flats.when == "start" and starts:
            steps.insert(0, flat)
        elif plan.flats.when == "end" and ends:
            steps.append(flat)
    if plan.darks.count:
        dark = {"kind": "dark", "wi": None, "wo": None}
        if plan.darks.when == "start" and starts:
            steps.insert(0, dark)
        elif plan.darks.when == "end" and ends:
            steps.append(dark)
    return steps


def estimate_duration(plan: Plan, n_poses: int, travel_s: float) -> float:
    """The plan estimator: travel plus, per pose, the settle time and the expected frames'
    exposures and downloads (``bracket.shot_overhead_s``), plus the darks and flats, s.

    ``n_poses`` counts sample poses and the reference group once (its repeats are
    added); ``travel_s`` is the servo travel of the visiting order, s."""
    return _estimated_duration(plan, n_poses, travel_s)


def _estimated_duration(plan: Plan, n_pose: int, travel: float) -> float:
    b = plan.bracket
    per_frame = (
        b.exposures_s and float(np.mean(b.exposures_s)) or b.exposure_time_s
    ) + b.shot_overhead_s
    n_ref = len(plan.reference.poses)
    n_pose += n_ref * (plan.reference_repeats(n_pose - n_ref) - 1) if n_ref else 0
    est = travel + n_pose * (plan.settle_s + _expected_frames(plan) * per_frame)
    if plan.darks.count:
        n_t = len(plan.darks.exposure_times_s) or (len(b.exposures_s) or 3)
        n_t += 1 if plan.flats.count else 0
        est += plan.darks.count * n_t * per_frame
    if plan.flats.count:
        est += plan.flats.count * (plan.flats.exposure_s + b.shot_overhead_s)
    return est


def _joint_pose_schedule(
    plan: Plan,
    expanded: ExpandedPlan,
    kinematics: Any,
    start_joints: Mapping[str, float],
    tell: Callable[[str, int, int], None],
) -> Schedule:
    """The schedule of a joint-pose plan: the poses in the plan's order (their order
    decides the side each joint approaches from, so nothing is reordered), reference
    poses as a group at the start or end, darks as for a grid plan."""
    joint_steps = [p.to_json() for p in expanded.poses if p.kind != "reference"]
    ref_steps = [p.to_json() for p in expanded.poses if p.kind == "reference"]
    steps = [dict(s) for s in with_reference_groups(joint_steps, ref_steps, plan)]
    steps = with_calibration_steps(steps, plan)
    tell("dry run", 0, len(steps))
    approach: dict[int, dict[str, int]] = {}
    joints, refused = dry_run(steps, plan, kinematics, start_joints, approach)
    tell("dry run", len(steps), len(steps))
    travel, prev = 0.0, dict(start_joints)
    for k, step in enumerate(steps):
        if k not in joints:
            continue
        travel += kinematics.move_time(prev, joints[k])
        prev = joints[k]
        if step.get("joints") is not None and step["kind"] != "reference":
            # The directions these joints give with the approach signs the run will have
            # (on a nominal rig: the nominal forward, the approach does not matter).
            appr = [] if getattr(kinematics, "nominal", True) else [approach[k]]
            wi, wo = kinematics.forward(step["joints"], *appr)
            pose = Pose(_tuple3(wi), _tuple3(wo), step["kind"], step["joints"], step.get("label"))
            step.update(pose.to_json())
        step["joints"] = joints[k]
    for r in refused:
        steps[r.step]["refused"] = {"code": r.code, "message": r.message}
    est = _estimated_duration(plan, len(expanded.poses), travel)
    return Schedule(steps, expanded, travel, travel, est, refused)


def _tuple3(v: Any) -> tuple[float, float, float]:
    r = np.round(np.asarray(v, dtype=np.float64), 12) + 0.0
    return (float(r[0]), float(r[1]), float(r[2]))
