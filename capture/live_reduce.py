"""The reduction of a session while it is captured: each pose measured once it is done.

:class:`LiveReduction` measures a session's poses through the reduction's own per-pose
path (:class:`gonio.capture.reduce._PoseRun`, as :mod:`gonio.capture.adaptive_reduce`
does) as their ``pose_done`` records arrive, and :meth:`LiveReduction.finish` then does
what :func:`gonio.capture.reduce.reduce_session` does after its measurement -- the
calibration of the samples, ``reduction.json``, the plot, one output set -- so the files
are the same as a reduction of the finished session (``tests/e2e/test_demo_overlap.py``
compares them).  A pose's measurement needs nothing but its own frames when the session
has no dark frames, no flat fields and no fitted light profile (darks and flats are
shot at the end and enter every pose; a fitted profile needs every pose first): for any
other session :meth:`finish` is the plain :func:`reduce_session`, measured from scratch.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

from gonio.capture.frame_loader import FrameLoader, load_frame
from gonio.capture.journal import read_journal
from gonio.capture.reduction_config import ReductionSetup

__all__ = ["LiveReduction"]

log = logging.getLogger(__name__)


def _live_ok(setup: ReductionSetup, records: list[dict[str, Any]]) -> bool:
    """Whether poses can be measured one by one as they come (see the module)."""
    if setup.light_profile == "fit":
        return False
    return not any(r.get("type") == "shot" and r.get("kind") in ("dark", "flat") for r in records)


class LiveReduction:
    """Measure a session's poses as they are done; write its reduction at the end.

    Parameters
    ----------
    session_dir
        The session (its manifest, journal and ``reduction.toml`` exist).
    setup
        The reduction facts (``reduce_session``'s ``setup``).
    """

    def __init__(self, session_dir: str | os.PathLike, setup: ReductionSetup) -> None:
        self.session = Path(session_dir)
        self.setup = setup
        self._run: Any = None
        self._measured: list[int] = []
        self._live = setup.light_profile != "fit"

    def add(self) -> int:
        """Measure every pose done since the last call (in journal order); the number
        measured now.  Nothing, once the session turns out to need the whole-session
        path (a dark or flat frame)."""
        if not self._live:
            return 0
        from gonio.capture.manifest import load_manifest
        from gonio.capture.reduce import _kinematics, _PoseRun, _shots_by_pose

        records = read_journal(self.session / "journal.jsonl")
        if not _live_ok(self.setup, records):
            self._live, self._run = False, None
            return 0
        shots, done = _shots_by_pose(records)
        todo = [
            p
            for p in sorted(shots)
            if shots[p]
            and shots[p][0].get("kind") in ("sample", "reference")
            and p not in self._measured
        ]
        # in journal order, and only a leading run of done poses: the order of the
        # measurements is the reduction's
        ready = []
        for p in todo:
            if p not in done:
                break
            ready.append(p)
        if not ready:
            return 0
        if self._run is None:
            run = _PoseRun(
                self.session, self.setup, _kinematics(load_manifest(self.session)), records
            )
            if run.setup.signature is None:  # the session camera's: the first frame's
                first = next(
                    (r for recs in shots.values() for r in recs if r.get("kind") != "dark"), None
                )
                if first is not None:
                    fr = run._checked([first], [load_frame(self.session, None, first)])[0]
                    if fr is not None:
                        run.setup = run.setup.replace(signature=fr.signature)
            self._run = run
        run = self._run
        run.records = records
        with FrameLoader(self.session, run.setup.signature, 1) as loader:
            if not self._measured:
                self._masters = run._master_darks(loader, shots)
                run._radiometric_calibration(loader, shots, self._masters)
            for p in ready:
                run._measure(p, shots[p], loader, self._masters)
                self._measured.append(p)
        return len(ready)

    def finish(self, *, plot: bool = True) -> Any:
        """The session's reduction (a :class:`gonio.capture.reduce.ReductionResult`),
        written as :func:`gonio.capture.reduce.reduce_session` writes it."""
        from gonio.capture.adaptive_reduce import with_round_steps
        from gonio.capture.journal import session_file
        from gonio.capture.manifest import load_manifest, refuse_calibration_session
        from gonio.capture.reduce import (
            PLOT_FILE,
            SAMPLES_FILE,
            SUMMARY_FILE,
            ReductionResult,
            _shots_by_pose,
            _write_json,
            journal_stamps,
            output_lock,
            reduce_session,
            retention,
        )
        from gonio.texels import TEXELS_FILE

        session = self.session
        self.add()
        records = read_journal(session / "journal.jsonl")
        shots, done = _shots_by_pose(records)
        poses = sorted(
            p
            for p, recs in shots.items()
            if recs and recs[0].get("kind") in ("sample", "reference")
        )
        path = session / SAMPLES_FILE
        if (
            not self._live
            or self._run is None
            or poses != self._measured
            or os.path.lexists(path.with_name(TEXELS_FILE))
        ):
            # darks, flats, a fitted profile, a pose not completed, an earlier texel
            # reduction's set: the whole-session path
            log.info("%s: reduced as a whole (not measured as it was captured)", session)
            return reduce_session(session, setup=self.setup, plot=plot)
        from gonio.capture.output_set import output_set
        from gonio.capture.samples_plot import plot_samples
        from gonio.dataset import save_samples
        from gonio.locks import hold_lock

        manifest = load_manifest(session)
        refuse_calibration_session(session, manifest)
        manifest = with_round_steps(manifest, records, session / "journal.jsonl")
        for rec in records:  # a journal naming a file outside the session is refused
            if rec.get("type") == "shot":
                session_file(session, rec)
        run = self._run
        run.records = records
        run.cal.stamps = journal_stamps(records)
        run.cal.kinds = {p: shots[p][0]["kind"] for p in poses}
        names = [path.name, SUMMARY_FILE, PLOT_FILE]
        with hold_lock(output_lock(path), f"output {path}"):
            samples = run.samples(manifest)
            n_kept = int(samples.valid.sum())
            summary = run.summary(len(samples), n_kept, path)
            summary["retention"] = retention(manifest, run.measurements, run.setup.grid_xy)
            summary["texels"] = None
            summary["warnings"] = list(run.warnings)
            with output_set(path, names) as stage:
                save_samples(stage / path.name, samples)
                _write_json(stage / SUMMARY_FILE, summary)
                if plot:
                    plot_samples(samples, stage / PLOT_FILE)
            plot_path = path.with_name(PLOT_FILE) if plot else None
        return ReductionResult(
            path, len(samples), n_kept, dict(run.rejected), summary, plot_path, list(run.warnings)
        )
