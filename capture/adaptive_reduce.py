"""The reduction of an adaptive session as it goes: each round's new poses only.

:class:`IncrementalReduction` keeps one :class:`gonio.capture.reduce._PoseRun` (the
reduction's own per-pose path: frame checks, master darks, flat gain, ChArUco pose,
regions, radiometry) for the whole session, measures each pose once, when it is first
added, and calibrates the samples of every pose so far with the reference group shot at
the start.  What it returns is what ``gonio capture reduce`` would give for the poses so
far, with two differences that do not matter to a choice of poses: the light profile
is not fitted (``[light] profile = "fit"`` applies only to the final reduction) and
dark frames shot at the end are not there yet.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from gonio.capture.frame_loader import FrameLoader, load_frame
from gonio.capture.journal import read_journal
from gonio.capture.manifest import load_manifest, refuse_calibration_session
from gonio.capture.reduction_config import ReductionSetup, resolve_setup

__all__ = ["IncrementalReduction", "with_round_steps"]


def with_round_steps(
    manifest: Mapping[str, Any], records: list[dict[str, Any]], journal: Any = "journal.jsonl"
) -> dict[str, Any]:
    """The manifest document with its ``schedule`` extended by an adaptive session's
    journaled rounds (unchanged for any other session).

    Raises
    ------
    FileFormatError
        A round record is damaged (:func:`gonio.capture.adaptive.round_records`).
    """
    from gonio.capture.adaptive import adaptive_steps, round_records

    n = len(manifest.get("schedule") or [])
    extra = adaptive_steps(round_records(records, journal, n))
    if not extra:
        return dict(manifest)
    return {**manifest, "schedule": list(manifest.get("schedule") or []) + extra}


class IncrementalReduction:
    """Reduce a session's poses as they are added (see the module docstring).

    Parameters
    ----------
    session_dir
        The session.
    setup
        The reduction facts; None: the session's ``reduction.toml``
        (:func:`gonio.capture.reduction_config.resolve_setup`).
    """

    def __init__(self, session_dir: str | os.PathLike, setup: ReductionSetup | None = None) -> None:
        self.session = Path(session_dir)
        self._manifest = load_manifest(self.session)
        refuse_calibration_session(self.session, self._manifest)
        self.setup = setup if setup is not None else resolve_setup(self.session, self._manifest)
        self._run: Any = None
        self._masters: Any = None
        self._measured: set[int] = set()

    @property
    def measured(self) -> set[int]:
        """Journal numbers of the poses measured so far (sample and reference)."""
        return set(self._measured)

    def _start(self, records: list[dict[str, Any]], shots: dict[int, list[dict]]) -> None:
        from gonio.capture.reduce import _kinematics, _PoseRun

        run = _PoseRun(self.session, self.setup, _kinematics(self._manifest), records)
        if run.setup.signature is None:  # the session camera's: the first frame's
            first = next(
                (r for recs in shots.values() for r in recs if r.get("kind") != "dark"), None
            )
            if first is not None:
                fr = run._checked([first], [load_frame(self.session, None, first)])[0]
                if fr is not None:
                    run.setup = run.setup.replace(signature=fr.signature)
        with FrameLoader(self.session, run.setup.signature, 1) as loader:
            self._masters = run._master_darks(loader, shots)
            run._radiometric_calibration(loader, shots, self._masters)
        self._run = run

    def add(self, steps: Iterable[int]) -> Any:
        """Measure ``steps`` (journal numbers of completed poses) and every completed
        reference pose not measured yet; return the samples of all poses so far.

        Returns
        -------
        gonio.dataset.BRDFSamples
            As :func:`gonio.capture.reduce.reduce_session` writes them (calibrated with
            the reference poses measured so far).

        Raises
        ------
        SessionError
            No sample pose measured yet.
        ReductionError
            No usable reference frame (the irradiance cannot be calibrated).
        """
        from gonio.capture.reduce import _shots_by_pose, journal_stamps

        records = read_journal(self.session / "journal.jsonl")
        shots, done = _shots_by_pose(records)
        if self._run is None:
            self._start(records, shots)
        run = self._run
        run.records = records
        run.cal.stamps = journal_stamps(records)
        wanted = {int(k) for k in steps}
        todo = sorted(
            p
            for p, recs in shots.items()
            if p in done
            and p not in self._measured
            and recs
            and (
                recs[0].get("kind") == "reference"
                or (p in wanted and recs[0].get("kind") == "sample")
            )
        )
        with FrameLoader(self.session, run.setup.signature, 1) as loader:
            for p in todo:
                run._measure(p, shots[p], loader, self._masters)
                run.cal.kinds[p] = shots[p][0]["kind"]
                self._measured.add(p)
        run.warnings.clear()  # said again by each call: only this call's
        return run.samples(self._manifest)
