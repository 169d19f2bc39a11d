"""Adaptive sessions: the seed design, then rounds of advise -> journal -> order -> capture.

An ``[adaptive]`` plan (:class:`gonio.capture.plan.AdaptivePlan`) has a schedule of its
fixed part only (calibration steps at the start, the reference group, the seed design:
``manifest.json``'s ``schedule``).  :func:`adaptive_session_plan` runs it with the
session plan's own per-step machinery (:class:`gonio.capture.session_plan.PoseSteps`),
then, round after round:

1. asks the :class:`Advisor` (the composition root wires one that reduces the new poses
   and fits the candidate models: ``gonio.app.adaptive_advisor.FitAdvisor``) for the
   next batch, with the :class:`AdaptiveState` (the reachable candidates not yet
   measured, what was measured, the estimated session time so far);
2. cuts the batch to the pose and time budgets (the plan estimator:
   :func:`gonio.capture.schedule.estimate_duration`), orders it for the least servo
   travel (:mod:`gonio.capture.ordering`) from where the previous step left the rig, and
   dry-runs it (joints and path refusals, as :func:`gonio.capture.schedule.build_schedule`
   does for a grid);
3. journals the decision -- ``{"type": "adaptive_round", "round", "chosen_ids", "stop",
   "steps", "first_step", ...the advisor's record}`` -- *before* anything of it moves;
4. captures the batch (steps numbered on from the schedule's: ``first_step``, ...).

The stop (the advisor's target precision, ``max_poses``, ``max_time_s``, the pool
empty) is a round record too, whose ``steps`` are the calibration steps "at the end".
A resume replays the journaled rounds (their steps, not a new decision: a resumed
session takes the same poses even if a refit were not bit-identical) and asks the
advisor again only for a round that has no record.  The session's whole schedule is
:func:`session_steps` (the manifest's, then every round's ``steps``).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Generator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal, Protocol

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from gonio.capture.adaptive_pool import CandidatePool
from gonio.capture.manifest import ScheduleStep
from gonio.capture.messages import Checkpoint
from gonio.capture.ordering import move_time_matrix, order_poses
from gonio.capture.plan import Plan
from gonio.capture.schedule import dry_run, estimate_duration, with_calibration_steps
from gonio.capture.session_plan import PlanState, PoseSteps
from gonio.config import validation_message
from gonio.errors import FileFormatError, PoseRefused

__all__ = [
    "ROUND",
    "STOP_MAX_POSES",
    "STOP_MAX_TIME",
    "STOP_POOL_EMPTY",
    "AdaptiveState",
    "Advisor",
    "Decision",
    "adaptive_session_plan",
    "adaptive_steps",
    "round_records",
    "rounds_summary",
    "session_steps",
]

#: The journal record of a round.
ROUND = "adaptive_round"
STOP_MAX_POSES = "max_poses"
STOP_MAX_TIME = "max_time_s"
STOP_POOL_EMPTY = "pool empty"


@dataclass(frozen=True)
class AdaptiveState:
    """What an advisor is told before each round.

    Attributes
    ----------
    session_dir
        The session (its journal holds every shot so far).
    round
        The round about to be decided (0 after the seed design).
    measured_steps
        Journal numbers of the sample poses measured so far (skipped ones left out).
    new_steps
        Those measured since this process last asked (all of them at a first ask).
    pool_wi, pool_wo
        (K, 3) the reachable candidates not yet measured (sample frame, unit vectors).
    pool_ids
        (K,) their stable ids (positions in the session's candidate pool).
    elapsed_s
        Estimated session time so far (the plan estimator: travel + exposures +
        downloads), s.
    poses_done
        Sample poses measured so far.
    plan
        The session's plan.
    """

    session_dir: Path
    round: int
    measured_steps: list[int]
    new_steps: list[int]
    pool_wi: NDArray[np.float64]
    pool_wo: NDArray[np.float64]
    pool_ids: NDArray[np.int64]
    elapsed_s: float
    poses_done: int
    plan: Plan


@dataclass(frozen=True)
class Decision:
    """An advisor's answer: the pool ids to measure next (any order: the session orders
    them for travel), a stop reason (None: go on), and what to journal about it (JSON)."""

    chosen_ids: list[int]
    stop: str | None = None
    record: dict[str, Any] = field(default_factory=dict)


class Advisor(Protocol):
    """Chooses each round's batch (``gonio.app.adaptive_advisor.FitAdvisor``)."""

    def advise(self, state: AdaptiveState) -> Decision: ...


# --------------------------------------------------------------------------------------
# The journal's rounds


class _Round(BaseModel):
    model_config = ConfigDict(extra="allow")
    type: Literal["adaptive_round"]
    round: Annotated[int, Field(strict=True, ge=0)]
    first_step: Annotated[int, Field(strict=True, ge=0)]
    chosen_ids: list[Annotated[int, Field(strict=True, ge=0)]]
    stop: str | None = None
    steps: list[ScheduleStep]


def round_records(
    records: Sequence[Mapping[str, Any]], journal: Any = "journal.jsonl", n_schedule: int = 0
) -> list[dict[str, Any]]:
    """The journal's ``adaptive_round`` records, validated, in order.

    Parameters
    ----------
    n_schedule
        Steps in the manifest's schedule (the first round's steps follow them); 0: not
        checked.

    Raises
    ------
    FileFormatError
        A record lacks a field or holds a wrong value (record and field named), rounds
        are not numbered 0, 1, 2, ..., their steps do not follow each other, or a round
        follows the stop.
    """
    out: list[dict[str, Any]] = []
    expect = n_schedule
    for n, r in enumerate(records, 1):
        if r.get("type") != ROUND:
            continue
        try:
            _Round.model_validate(r)
        except ValidationError as exc:
            raise FileFormatError(
                journal, validation_message(exc, f"record {n} ({ROUND})")
            ) from None
        if r["round"] != len(out):
            raise FileFormatError(
                journal, f"record {n}: round {r['round']}, expected {len(out)}", "round"
            )
        if out and out[-1].get("stop") is not None:
            raise FileFormatError(journal, f"record {n}: a round after the stop", "stop")
        if n_schedule and r["first_step"] != expect:
            raise FileFormatError(
                journal,
                f"record {n}: first_step {r['first_step']}, expected {expect}",
                "first_step",
            )
        expect = r["first_step"] + len(r["steps"])
        out.append(dict(r))
    return out


def adaptive_steps(records: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Every round's ``steps``, in order (the steps after the manifest's schedule)."""
    return [dict(s) for r in records if r.get("type") == ROUND for s in r.get("steps") or []]


def session_steps(
    schedule: Sequence[Any], records: Sequence[Mapping[str, Any]]
) -> list[dict[str, Any]]:
    """A session's whole schedule: the manifest's steps (models or dicts), then the
    journaled rounds' (an adaptive session's; none for a grid)."""
    steps = [s.model_dump() if hasattr(s, "model_dump") else dict(s) for s in schedule]
    return steps + adaptive_steps(records)


def rounds_summary(records: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """One row per journaled round (``gonio capture inspect``): ``round``, ``poses``
    (chosen), ``model`` and ``rel_sigma`` (the winning fit's), ``stop``, ``advise_s``,
    ``batch_time_s``."""
    rows = []
    for r in records:
        if r.get("type") != ROUND:
            continue
        fit = r.get("fit") if isinstance(r.get("fit"), dict) else {}
        rows.append(
            {
                "round": r.get("round"),
                "poses": len(r.get("chosen_ids") or []),
                "poses_done": r.get("poses_done"),
                "model": fit.get("model"),
                "rel_sigma": fit.get("rel_sigma"),
                "stop": r.get("stop"),
                "advise_s": r.get("advise_s"),
                "batch_time_s": r.get("batch_time_s"),
            }
        )
    return rows


# --------------------------------------------------------------------------------------
# The plan


@dataclass
class _Planner:
    """Where the planned path has left the rig (joints and approach signs), and the
    servo travel of the path so far."""

    kinematics: Any
    joints: dict[str, float]
    approach: dict[str, int] | None = None
    travel_s: float = 0.0

    def follow(self, steps: list[dict[str, Any]], plan: Plan, first_step: int) -> None:
        """Dry-run ``steps`` from here: fill in each step's joints (and ``refused``) the
        way :func:`~gonio.capture.schedule.build_schedule` does, and move on."""
        if not any(s.get("wi") is not None for s in steps):
            return
        appr: dict[int, dict[str, int]] = {}
        joints, refused = dry_run(
            steps,
            plan,
            self.kinematics,
            self.joints,
            appr,
            start_approach=self.approach,
            first_step=first_step,
        )
        for r in refused:
            steps[r.step - first_step].setdefault("refused", {"code": r.code, "message": r.message})
        for k in sorted(joints):
            q = joints[k]
            steps[k - first_step].setdefault("joints", q)
            self.travel_s += float(self.kinematics.move_time(self.joints, q))
            self.joints, self.approach = dict(q), dict(appr[k])

    def ordered(self, pool: CandidatePool, ids: list[int]) -> tuple[list[int], list[float]]:
        """``ids`` in the order of least travel from here (each pose solved from home,
        as the grid's ordering does), and the cumulative travel time along it, s."""
        if len(ids) < 2:
            order = list(ids)
        else:
            home = []
            for k in ids:
                try:
                    home.append(self.kinematics.inverse(pool.wi[k], pool.wo[k]))
                except PoseRefused:
                    home.append(dict(self.joints))
            servos = getattr(getattr(self.kinematics, "config", None), "servos", None)
            D = move_time_matrix(home, self.kinematics.move_time, start=self.joints, servos=servos)
            tour = order_poses(D, start=0)
            order = [ids[t - 1] for t in tour[1:]]
        cum, prev, t = [], dict(self.joints), 0.0
        for k in order:
            try:
                q = self.kinematics.inverse(pool.wi[k], pool.wo[k], current=prev)
            except PoseRefused:
                q = prev
            t += float(self.kinematics.move_time(prev, q))
            cum.append(t)
            prev = q
        return order, cum


def _budgeted(
    plan: Plan,
    order: list[int],
    cum_travel: list[float],
    planner: _Planner,
    n_done: int,
    n_ref: int,
) -> tuple[list[int], str | None]:
    """The longest head of ``order`` within ``max_poses`` and ``max_time_s`` (the plan
    estimator), and the budget that stopped it when nothing fits."""
    a = plan.adaptive
    assert a is not None
    room = max(0, a.max_poses - n_done)
    if room == 0:
        return [], STOP_MAX_POSES
    order = order[:room]
    if a.max_time_s is not None:
        keep = 0
        for j in range(1, len(order) + 1):
            t = estimate_duration(plan, n_done + j + n_ref, planner.travel_s + cum_travel[j - 1])
            if t > a.max_time_s:
                break
            keep = j
        if keep == 0 and order:
            return [], STOP_MAX_TIME
        order = order[:keep]
    return order, None


def adaptive_session_plan(
    steps: Sequence[Mapping[str, Any]],
    plan: Plan,
    state: PlanState,
    forward: Callable[..., Any],
    read_noise_dn: float,
    *,
    session_dir: Path,
    records: Sequence[Mapping[str, Any]],
    pool: CandidatePool,
    advisor: Advisor,
    kinematics: Any,
    start_joints: Mapping[str, float],
    skipped: set[int] | None = None,
    clock: Callable[[], float] = time.perf_counter,
) -> Generator[Any, Any, None]:
    """The messages of an adaptive session (see the module docstring).

    Parameters
    ----------
    steps
        The manifest's schedule (the fixed part).
    plan, state, forward, read_noise_dn
        As :func:`gonio.capture.session_plan.session_plan`.
    session_dir
        The session (told to the advisor).
    records
        The journal as it was when the run or resume started (its rounds are replayed).
    pool
        The session's candidate pool.
    advisor
        Chooses each round's batch.
    kinematics, start_joints
        The rig's kinematics (ordering and dry run of each batch) and its park pose.
    skipped
        Steps the journal already closes as skipped.
    clock
        Wall clock for ``advise_s`` (the only figure of a round that is not reproducible).
    """
    a = plan.adaptive
    assert a is not None
    poses = PoseSteps(plan, state, forward, read_noise_dn)
    journaled = round_records(records, n_schedule=len(steps))
    ext: list[dict[str, Any]] = [dict(s) for s in steps]
    done = set(state.done)
    skipped = set(skipped or ())
    planner = _Planner(kinematics, dict(start_joints))
    planner.follow([dict(s) for s in ext], plan, 0)  # where the schedule leaves the rig
    n_ref = sum(1 for s in ext if s["kind"] == "reference")
    told: set[int] = set()

    def run(new: list[dict[str, Any]]) -> Generator[Any, Any, None]:
        for s in new:
            k = len(ext)
            ext.append(s)
            yield from poses.step(k, s)
            done.add(k)

    fixed = list(ext)
    ext.clear()
    yield from run(fixed)
    rnd = 0
    while True:
        if rnd < len(journaled):
            rec = journaled[rnd]
            new = [dict(s) for s in rec["steps"]]
            planner.follow([dict(s) for s in new], plan, len(ext))
        else:
            rec, new = _decide(
                rnd,
                plan,
                pool,
                advisor,
                planner,
                ext,
                done,
                skipped | poses.skipped,
                told,
                n_ref,
                session_dir,
                clock,
            )
            yield Checkpoint(rec)  # journaled (fsynced) before anything of it moves
        yield from run(new)
        if rec.get("stop") is not None:
            return
        rnd += 1


def _decide(
    rnd: int,
    plan: Plan,
    pool: CandidatePool,
    advisor: Advisor,
    planner: _Planner,
    ext: list[dict[str, Any]],
    done: set[int],
    skipped: set[int],
    told: set[int],
    n_ref: int,
    session_dir: Path,
    clock: Callable[[], float],
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Ask the advisor, cut to the budgets, order, dry-run: the round's record and steps."""
    a = plan.adaptive
    assert a is not None
    measured = [
        k for k, s in enumerate(ext) if s["kind"] == "sample" and k in done and k not in skipped
    ]
    taken = {int(s["pool_id"]) for s in ext if s.get("pool_id") is not None}
    left = np.array([k for k in range(len(pool)) if k not in taken], dtype=np.int64)
    elapsed = estimate_duration(plan, len(measured) + n_ref, planner.travel_s)
    state = AdaptiveState(
        session_dir=Path(session_dir),
        round=rnd,
        measured_steps=measured,
        new_steps=[k for k in measured if k not in told],
        pool_wi=pool.wi[left] if len(left) else np.zeros((0, 3)),
        pool_wo=pool.wo[left] if len(left) else np.zeros((0, 3)),
        pool_ids=left,
        elapsed_s=float(elapsed),
        poses_done=len(measured),
        plan=plan,
    )
    stop: str | None = None
    if not len(left):
        decision, advise_s = Decision([], STOP_POOL_EMPTY, {}), 0.0
    elif len(measured) >= a.max_poses:
        decision, advise_s = Decision([], STOP_MAX_POSES, {}), 0.0
    else:
        t0 = clock()
        decision = advisor.advise(state)
        advise_s = clock() - t0
        told.update(measured)
    stop = decision.stop
    ok = set(left.tolist())
    wanted = list(dict.fromkeys(int(k) for k in decision.chosen_ids))
    ignored = [k for k in wanted if k not in ok]
    wanted = [k for k in wanted if k in ok]
    chosen: list[int] = []
    batch_time = 0.0
    if stop is None:
        if not wanted:
            stop = STOP_POOL_EMPTY
        else:
            order, cum_all = planner.ordered(pool, wanted)
            chosen, why = _budgeted(plan, order, cum_all, planner, len(measured), n_ref)
            if not chosen:
                stop = why
    first = len(ext)
    if stop is None:
        new = [pool.pose(k).to_json() for k in chosen]
        travel0 = planner.travel_s
        planner.follow(new, plan, first)
        batch_time = estimate_duration(plan, len(chosen), planner.travel_s - travel0) - (
            estimate_duration(plan, 0, 0.0)
        )
    else:
        new = with_calibration_steps([], plan, starts=False)
    rec: dict[str, Any] = {
        **{k: v for k, v in decision.record.items() if k not in ("type", "steps")},
        "type": "adaptive_round",
        "round": rnd,
        "chosen_ids": chosen,
        "stop": stop,
        "first_step": first,
        "steps": new,
        "poses_done": len(measured),
        "pool_left": int(len(left)),
        "elapsed_s": round(float(elapsed), 6),
        "batch_time_s": round(float(batch_time), 6),
        "advise_s": round(float(advise_s), 6),
    }
    if ignored:
        rec["ignored_ids"] = ignored
    if len(chosen) < len(wanted) and stop is None:
        rec["cut_to_budget"] = {"asked": len(wanted), "kept": len(chosen)}
    return rec, new
