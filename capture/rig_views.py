"""A rig-calibration session's frames as observations: board corners and mirror spots.

Reads the session's journal (the encoder readings ``joints`` and the approach direction
``approach`` of each pose, `DEVELOPING.md` "Session directory") and its frames, and
turns every pose into what :mod:`gonio.rig.calibration` fits:

- the holder's ChArUco corners -> :class:`gonio.rig.calibration_data.BoardObservation`
  with the corners in the SAMPLE frame (``p_sample = R p_board + t``, ``BoardSpec.transform``);
- at steps of kind ``"mirror"`` the light's image in the mirror ->
  :class:`gonio.rig.calibration_data.SpotObservation` (and the board corners too, which
  are visible around the mirror).

A pose where the board or the spot is not found is a :class:`ViewProblem` with the
reason, not an error: a calibration plan has many poses and the solver decides whether
the rest suffice.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gonio.capture.camera_calibration import detect_view
from gonio.capture.fiducials import BoardSpec
from gonio.capture.frame_loader import load_frame
from gonio.capture.journal import latest_shots, read_journal
from gonio.capture.mirror_spot import find_spot
from gonio.capture.pose_measure import _detection_frame
from gonio.capture.raw import RawFrame
from gonio.errors import ReductionError, SessionError
from gonio.rig.calibration_data import BoardObservation, SpotObservation

__all__ = ["ViewProblem", "calibration_observations", "observation_approach"]

#: Shot kinds that show the board (``"mirror"`` also shows the light's spot).
VIEW_KINDS = ("sample", "mirror")


@dataclass(frozen=True)
class ViewProblem:
    """A pose that gave no observation (or only some), and why."""

    label: str
    pose: int
    what: str  # "board" | "spot" | "frames"
    reason: str


def observation_approach(record: Mapping[str, Any]) -> dict[str, int]:
    """The journal's ``approach`` of a shot, one sign per joint; 0 (unknown) for every
    joint of a journal written before it was recorded."""
    joints = record.get("joints") or {}
    given = record.get("approach") or {}
    return {str(j): int(np.sign(given.get(j, 0))) for j in joints}


def calibration_observations(
    session_dir: str | os.PathLike,
    board: BoardSpec,
    *,
    min_corners: int = 6,
) -> tuple[list[BoardObservation], list[SpotObservation], list[ViewProblem]]:
    """Observations of every pose of a calibration session.

    Parameters
    ----------
    session_dir
        The session (its ``journal.jsonl`` and ``raw/`` frames).
    board
        The holder's board.
    min_corners
        Fewest corners for a board observation.

    Returns
    -------
    boards, spots, problems
        Board observations (poses of kind ``sample`` and ``mirror``, journal order), spot
        observations (``mirror`` poses) and the poses that gave nothing, with reasons.

    Raises
    ------
    SessionError
        Not a session (no journal).
    FileFormatError
        A damaged journal.
    """
    session_dir = Path(session_dir)
    journal = session_dir / "journal.jsonl"
    if not journal.is_file():
        raise SessionError(f"{session_dir}: not a session (no journal.jsonl)")
    by_pose: dict[int, list[Mapping[str, Any]]] = {}
    for (pose, _frame), rec in sorted(latest_shots(read_journal(journal)).items()):
        if rec.get("kind", "sample") in VIEW_KINDS:
            by_pose.setdefault(int(pose), []).append(rec)
    R, t = board.transform()
    boards: list[BoardObservation] = []
    spots: list[SpotObservation] = []
    problems: list[ViewProblem] = []
    for pose, recs in by_pose.items():
        label = f"pose {pose}"
        first = recs[0]
        joints = {str(k): float(v) for k, v in (first.get("joints") or {}).items()}
        approach = observation_approach(first)
        frames: list[RawFrame] = []
        for rec in recs:
            fr, problem = load_frame(session_dir, None, rec)
            if fr is None:
                problems.append(ViewProblem(label, pose, "frames", str(problem)))
            else:
                frames.append(fr)
        if not frames:
            continue
        view = detect_view(_detection_frame(frames), board, label=label, min_corners=min_corners)
        if view.problem is not None:
            problems.append(ViewProblem(label, pose, "board", view.problem))
        else:
            boards.append(
                BoardObservation(
                    label, joints, approach, view.object_points @ R.T + t, view.image_points
                )
            )
        if first.get("kind") == "mirror":
            try:
                u, v, info = find_spot(frames, name=label)
            except ReductionError as exc:
                problems.append(ViewProblem(label, pose, "spot", str(exc)))
            else:
                r0, r1, c0, c1 = info["box"]
                # pixel centres of the box's outer pixels, widened by half a pixel
                box = (c0 - 0.5, r0 - 0.5, c1 - 0.5, r1 - 0.5)
                spots.append(SpotObservation(label, joints, approach, np.array([u, v]), box))
    return boards, spots, problems
