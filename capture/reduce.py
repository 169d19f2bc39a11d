"""Reduce a capture session to BRDF samples: ``reduce_session(SESSION/) -> samples.h5``.

For every pose of the session (see DEVELOPING.md, "Session directory"):

1. the RAW frames are checked against their journal record and the session's camera
   (CFA pattern and size) and decoded on the mosaic, in worker threads that run ahead of
   the measurement (:mod:`gonio.capture.frame_loader`); the matching master dark (same
   exposure time and ISO) is subtracted;
2. the pose is measured (:func:`gonio.capture.pose_measure.measure_pose`): the holder's
   ChArUco board gives the camera pose, the sample's central area is split into
   ``grid x grid`` regions, each one BRDF sample with its own ``wo`` and ``wi`` (the light's
   position from the rig's kinematics at the joint angles read back), the bracket is
   merged and each region averaged per CFA channel;
3. the reference target's poses give the light's radiance in camera units, and each
   sample region's BRDF follows (:mod:`gonio.capture.radiometric`).

The camera, board, sample, light and noise facts come from ``SESSION/reduction.toml``
(:mod:`gonio.capture.reduction_config`).  Results are taken in journal order, so the
output is the same for any number of threads.  Each region is one sample of
``samples.h5`` (:mod:`gonio.dataset`); its ``frames`` entry lists the bracket's RAW files
joined by ``;``.  Nothing in ``raw/`` is touched; ``samples.h5``, the summary
``reduction.json`` (samples kept and rejected, with reasons) and ``samples.png`` are
written as one set (:mod:`gonio.capture.output_set`: a kill leaves the old set or the
new), by one process at a time (a lock beside the output), and the same session gives
the same files.
"""

from __future__ import annotations

import functools
import json
import os
import warnings
from collections import Counter, defaultdict
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gonio.capture.aperture import aperture_bias, region_moments
from gonio.capture.budget import (
    POSE_MODE_NAMES,
    TERMS,
    budget_rows,
    camera_modes,
    direction_variance,
    geometry_std,
    local_log_gradient,
    pose_modes,
    rig_shifts,
    session_modes,
)
from gonio.capture.fiducials import CameraPose
from gonio.capture.frame_loader import PREFETCH_POSES, FrameLoader, default_threads, load_frame
from gonio.capture.noise import NoiseModel
from gonio.capture.output_set import output_set
from gonio.capture.pose_measure import (
    PoseMeasurement,
    board_trusted,
    detect_board,
    invalid_pose,
    measure_pose,
    reported_pose,
)
from gonio.capture.radiometric import (
    DriftModel,
    LightProfile,
    brdf_of,
    dark_offset_std,
    drift_model,
    effective_sites,
    fit_light_profile,
    flat_rel_std,
    irradiance_rel_std,
    light_scale,
    region_flat_rel_std,
    stray_rel_std,
)
from gonio.capture.raw import CHANNELS, RawFrame, apply_flat, subtract_dark
from gonio.capture.reduction_config import (
    CONFIG_FILE,
    NOISE_FILE,
    ReductionSetup,
    resolve_setup,
)
from gonio.capture.samples_plot import plot_samples
from gonio.capture.texel_reduce import texel_levelled
from gonio.dataset import save_samples
from gonio.errors import GonioError, ReductionError, SessionError
from gonio.locks import hold_lock
from gonio.texels import ORIENTATION, TEXELS_FILE, save_texels

__all__ = [
    "CONFIG_FILE",
    "NOISE_FILE",
    "PLOT_FILE",
    "RADIANCE_UNITS",
    "IRRADIANCE_UNITS",
    "SAMPLES_FILE",
    "SUMMARY_FILE",
    "TEXELS_FILE",
    "IncrementalReduction",
    "budget_gradient_chart",
    "ReductionResult",
    "ReductionSetup",
    "default_threads",
    "RETENTION_UP_TO_DEG",
    "output_lock",
    "reduce_session",
    "resolve_setup",
    "retention",
]

SAMPLES_FILE = "samples.h5"
SUMMARY_FILE = "reduction.json"
PLOT_FILE = "samples.png"
#: What the ``radiance`` dataset holds: camera DN per exposure factor
#: (:meth:`gonio.capture.raw.RawFrame.exposure_factor`: s x ISO/100 / N^2), vignetting
#: corrected; relative, not W/(sr m^2).
RADIANCE_UNITS = "DN/(s ISO/100 / N^2) (camera units, relative radiance)"
#: What the ``irradiance`` dataset holds: the light's radiance in the same camera units
#: times the geometry factor (sr); ``brdf = radiance / irradiance``.
IRRADIANCE_UNITS = "DN/(s ISO/100 / N^2) sr (camera units, relative irradiance)"


@dataclass
class ReductionResult:
    """What :func:`reduce_session` did.

    Attributes
    ----------
    path
        The written ``samples.h5``.
    n_samples, n_kept
        Samples written, and those with no flag.
    rejected
        Reason -> number of samples (or frames) rejected for it.
    summary
        The JSON summary written next to the samples.
    plot
        The plot file, or None.
    warnings
        What the session lacks and what it costs (no flats, no darks, one reference
        group, a light profile the fit does not determine), also in ``reduction.json["warnings"]``.
    """

    path: Path
    n_samples: int
    n_kept: int
    rejected: dict[str, int]
    summary: dict[str, Any]
    plot: Path | None
    warnings: list[str] = field(default_factory=list)


def output_lock(path: str | os.PathLike) -> Path:
    """The lock file a reduction holds while it writes ``path`` (``.NAME.lock`` beside it)."""
    p = Path(path)
    return p.with_name(f".{p.name}.lock")


def reduce_session(
    session_dir: str | os.PathLike,
    *,
    out: str | os.PathLike | None = None,
    noise: NoiseModel | None = None,
    setup: ReductionSetup | None = None,
    plot: bool = True,
    progress: Callable[[int, int], None] | None = None,
    threads: int | None = None,
    texels: tuple[int, int] | None = None,
) -> ReductionResult:
    """Reduce a session's RAW frames to calibrated BRDF samples (``samples.h5``).

    Parameters
    ----------
    session_dir
        The session directory (manifest, journal, raw/, reduction.toml).
    out
        Output file; ``SESSION/samples.h5`` by default.  ``reduction.json`` and
        ``samples.png`` are written beside it.
    noise
        Noise model overriding the session's (``noise.json`` / ``reduction.toml``).
    setup
        All reduction facts, overriding what the session says
        (:func:`gonio.capture.reduction_config.resolve_setup` otherwise).
    plot
        Write ``samples.png`` (angle-domain plot) next to the output.
    progress
        Called as ``progress(done, total)`` after each pose.
    threads
        Threads, this one included: the others read, hash and decode frames ahead while
        poses are measured (:func:`default_threads` when None; 1 does everything in
        this thread).  The output is the same for any number.
    texels
        ``(nx, ny)``: also write the per-texel file ``texels.h5`` beside the output
        (:mod:`gonio.texels`), with the region grid made the texel grid
        (:mod:`gonio.capture.texel_reduce`: ``nx x ny`` regions over the whole sample,
        ``roi_fraction = 1``, overriding the setup's); ``samples.h5`` then holds the same
        samples pooled.  Without it, a ``texels.h5`` of an earlier texel reduction leaves
        with the rest of that output set.

    Returns
    -------
    ReductionResult

    Raises
    ------
    SessionError
        Not a session directory, no ``reduction.toml``, or nothing to reduce.
    ReductionError
        No usable reference frames (the irradiance cannot be calibrated); ``texels``
        finer than the camera resolves
        (:func:`gonio.capture.texel_reduce.texel_resolution`), refused before any frame
        is decoded.
    gonio.locks.LockedError
        Another process is writing the same output (nothing is written).
    """
    from gonio.capture.journal import read_journal, session_file
    from gonio.capture.manifest import load_manifest, refuse_calibration_session
    from gonio.capture.session_dir import session_state

    session = Path(session_dir)
    manifest = load_manifest(session)
    refuse_calibration_session(session, manifest)
    records = read_journal(session / "journal.jsonl")
    # the records checked as `capture inspect` and resume check them: a malformed field
    # is named, not a traceback or NaN samples
    session_state(records, session / "journal.jsonl")
    manifest = with_round_steps(manifest, records, session / "journal.jsonl")  # adaptive
    for rec in records:  # a journal naming a file outside the session is refused outright
        if rec.get("type") == "shot":
            session_file(session, rec)
    if setup is None:
        setup = resolve_setup(session, manifest, noise)
    elif noise is not None:
        setup = setup.replace(noise=noise)
    kin = _kinematics(manifest)
    resolution = None
    if texels is not None:
        from gonio.capture.texel_reduce import texel_resolution, texel_setup

        texels = (int(texels[0]), int(texels[1]))
        setup = texel_setup(setup, texels)
        resolution = texel_resolution(setup, texels, _sample_cameras(kin, records))
    path = Path(out) if out is not None else session / SAMPLES_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    names = [path.name, SUMMARY_FILE, PLOT_FILE]
    if texels is not None or _texels_of_this_set(path):
        # texels.h5 joins the set when written, and when an earlier texel reduction's is
        # there (it then leaves with its set); a file of that name that is not ours is
        # never touched
        names.append(TEXELS_FILE)
    if texels is not None:
        _refuse_foreign_texels(path.with_name(TEXELS_FILE), path)
    with hold_lock(output_lock(path), f"output {path}"):
        run = _PoseRun(session, setup, kin, records, texels=texels)
        run.warnings.extend(_beyond_schedule(records, manifest))
        run.measure_all(default_threads() if threads is None else max(1, int(threads)), progress)
        samples = run.samples(manifest)
        n_kept = int(samples.valid.sum())
        summary = run.summary(len(samples), n_kept, path)
        summary["retention"] = retention(manifest, run.measurements, run.setup.grid_xy)
        texel_doc = None
        if texels is not None:
            texel_doc = _texel_arrays_and_summary(run, samples, session, texels, resolution)
        summary["texels"] = None if texel_doc is None else texel_doc[1]
        summary["warnings"] = list(run.warnings)  # with the texel file's, if any
        # One set: a kill leaves the old samples, summary, plot and texels, or the new
        # ones; a reduction without --texels drops an earlier one's texels.h5 with the
        # rest of its set.
        with output_set(path, names) as stage:
            save_samples(stage / path.name, samples)
            if texel_doc is not None:
                save_texels(stage / TEXELS_FILE, **texel_doc[0])
            _write_json(stage / SUMMARY_FILE, summary)
            if plot:
                plot_samples(samples, stage / PLOT_FILE)
        plot_path = path.with_name(PLOT_FILE) if plot else None
    return ReductionResult(
        path, len(samples), n_kept, dict(run.rejected), summary, plot_path, list(run.warnings)
    )


def _beyond_schedule(records: list[dict[str, Any]], manifest: Mapping[str, Any]) -> list[str]:
    """A warning for sample and reference shots of poses the schedule does not have: they
    are not reduced, and a journal edited by hand lost them without a word."""
    n = len(manifest.get("schedule") or [])
    poses = sorted(
        {
            r["pose"]
            for r in records
            if r.get("type") == "shot"
            and r.get("kind") in ("sample", "reference")
            and isinstance(r.get("pose"), int)
            and r["pose"] >= n
        }
    )
    if not poses:
        return []
    shown = ", ".join(map(str, poses[:5])) + (" ..." if len(poses) > 5 else "")
    return [
        f"the journal has sample or reference shots of pose(s) {shown}, beyond the "
        f"schedule's {n} steps (the manifest or the journal was edited?): not reduced"
    ]


def _texels_of_this_set(path: Path) -> bool:
    """Whether ``texels.h5`` beside ``path`` is the link into ``path``'s output set that an
    earlier texel reduction made."""
    from gonio.capture.output_set import set_folder

    t = path.with_name(TEXELS_FILE)
    return t.is_symlink() and os.readlink(t) == f"{set_folder(path).name}/{TEXELS_FILE}"


def _refuse_foreign_texels(tex: Path, path: Path) -> None:
    """Refuse to replace a ``texels.h5`` that neither this output's set nor gonio wrote."""
    if not os.path.lexists(tex) or _texels_of_this_set(path):
        return
    import h5py

    try:
        with h5py.File(tex, "r") as f:
            ours = f.attrs.get("schema") == "gonio.texels"
    except OSError:
        ours = False
    if not ours:
        raise ReductionError(
            f"{tex} exists and is not a gonio texel file: move it away first (a texel "
            "reduction writes texels.h5 beside its output; nothing was written)"
        )


def _sample_cameras(
    kin: Any, records: list[dict[str, Any]]
) -> dict[int, tuple[NDArray[np.float64], NDArray[np.float64]]]:
    """Sample pose -> the rig's reported camera (position, world-to-camera rotation),
    from the journal's last shot of each pose (poses whose camera is unknown left out)."""
    last: dict[int, dict[str, Any]] = {}
    for r in records:
        if r.get("type") == "shot" and r.get("kind") == "sample":
            last[int(r["pose"])] = r
    out = {}
    for p, r in last.items():
        wi = np.asarray(r.get("wi_achieved") or r.get("wi_requested") or [0, 0, 1], float)
        wo = np.asarray(r.get("wo_achieved") or r.get("wo_requested") or [0, 0, 1], float)
        try:
            _, _, cam = _rig_pose(kin, r.get("joints"), wi, wo, r.get("approach"))
        except ReductionError:
            continue
        out[p] = cam
    return out


def _texel_arrays_and_summary(
    run: _PoseRun,
    samples: Any,
    session: Path,
    texels: tuple[int, int],
    resolution: Any,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """``save_texels``'s arguments and ``reduction.json["texels"]``."""
    from gonio.capture.texel_reduce import modes_omitted, texel_arrays

    samples_m = [m for m in run.measurements if m.kind == "sample"]
    nx, ny = run.setup.grid_xy
    m_modes = 0 if samples.geometry_modes is None else samples.geometry_modes.shape[1]
    omitted = modes_omitted(nx * ny, len(samples_m), m_modes)
    if omitted:
        run.warnings.append(omitted)
    arrays = texel_arrays(
        samples,
        [len(m.flags) for m in samples_m],
        [m.pose for m in samples_m],
        (nx, ny),
        with_modes=omitted is None,
    )
    attrs = dict(samples.attrs)
    attrs["session_created"] = attrs.pop("session", "")
    attrs["session"] = str(session)
    doc = dict(
        arrays,
        texels=texels,
        sample_size=tuple(run.setup.sample_size),
        channels=samples.channels,
        attrs=attrs,
        units=dict(samples.units),
    )
    usable = arrays["flags"] == 0
    with np.errstate(invalid="ignore"):
        usable &= np.isfinite(arrays["brdf"]).all(axis=2)
    per_texel = usable.sum(axis=1)
    summary = {
        "file": TEXELS_FILE,
        "texels": list(texels),
        "n_texels": int(nx * ny),
        "sample_size_m": list(run.setup.sample_size),
        "orientation": ORIENTATION,
        "poses": len(samples_m),
        "samples": int(usable.size),
        "kept": int(usable.sum()),
        "kept_per_texel": {
            "min": int(per_texel.min()),
            "median": float(np.median(per_texel)),
            "max": int(per_texel.max()),
        },
        "texels_without_samples": int((per_texel == 0).sum()),
        "chunk_texels": None,  # below
        "region_order": "region r = iy * NX + ix (iy from -y) is texel (NY - 1 - iy) * NX + ix",
        "grid": [nx, ny],
        "roi_fraction": run.setup.roi_fraction,
        # image pixels left out along each texel's boundaries (texel_reduce.TEXEL_MARGIN_PX)
        "boundary_margin_px": run.setup.region_margin_px,
        "resolution": None if resolution is None else resolution.to_json(),
        "samples_h5": "the same samples pooled (one per texel and sample pose)",
        "geometry_modes": "geometry_modes" in arrays,
        "geometry_modes_omitted": omitted,
    }
    from gonio.texels import chunk_texels_for

    m = arrays["geometry_modes"].shape[2] if "geometry_modes" in arrays else 0
    # the rule save_texels applies by default, fixed here so the summary states it
    k = chunk_texels_for(nx * ny, len(samples_m), 8 * m * 6 if m else 8 * 3)
    summary["chunk_texels"] = doc["chunk_texels"] = k
    return doc, summary


@dataclass
class _PoseRun:
    """The measurement of a session's poses, and what went wrong on the way."""

    session: Path
    setup: ReductionSetup
    kin: Any
    records: list[dict[str, Any]]
    measurements: list[PoseMeasurement] = field(default_factory=list)
    failed_poses: list[dict[str, Any]] = field(default_factory=list)
    frame_problems: dict[str, str] = field(default_factory=dict)
    rejected: Counter[str] = field(default_factory=Counter)
    light: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
    # the radiometric calibration (issue 16): see _radiometric_calibration
    cal: _Radiometry = field(default_factory=lambda: _Radiometry())
    warnings: list[str] = field(default_factory=list)
    #: pose -> (light position, journaled joints, approach): what the budget's geometry
    #: modes move (:mod:`gonio.capture.budget`)
    pose_inputs: dict[int, tuple[Any, Any, Any]] = field(default_factory=dict)
    budget_summary: dict[str, Any] = field(default_factory=dict)
    #: (nx, ny) of a texel reduction (its regions are texels), else None
    texels: tuple[int, int] | None = None
    #: pose -> _rig_of's value (the rig's kinematics, once per pose)
    _rig_cache: dict[int, tuple[Any, ...]] = field(default_factory=dict)
    #: _geometry_modes' value
    _modes: tuple[Any, Any] | None = None
    #: pose -> ((joints, approach), _pose_shifts' value at them)
    _shift_cache: dict[int, tuple[Any, tuple[Any, Any, Any]]] = field(default_factory=dict)
    #: pose -> the dark term in radiance units of an undarked pose (_radiometric_terms)
    _dark_std: dict[int, NDArray[np.float64]] = field(default_factory=dict)

    def measure_all(self, threads: int, progress: Callable[[int, int], None] | None) -> None:
        """Decode and measure every sample and reference pose, in journal order."""
        shots, done = _shots_by_pose(self.records)
        self.cal.stamps = journal_stamps(self.records)
        if self.setup.signature is None:  # the session camera's: the first frame's
            first = next(
                (r for recs in shots.values() for r in recs if r.get("kind") != "dark"), None
            )
            if first is not None:
                fr = self._checked([first], [load_frame(self.session, None, first)])[0]
                if fr is not None:
                    self.setup = self.setup.replace(signature=fr.signature)
        with FrameLoader(self.session, self.setup.signature, threads) as loader:
            masters = self._master_darks(loader, shots)
            self._radiometric_calibration(loader, shots, masters)
            poses = sorted(
                p
                for p, recs in shots.items()
                if recs and recs[0].get("kind") in ("sample", "reference")
            )
            self.cal.kinds = {p: shots[p][0]["kind"] for p in poses}
            if self.setup.light_profile == "fit":
                self._fit_profile_first(poses, shots, done, loader, masters)
            for i, p in enumerate(poses):
                if p in done:
                    # keep the worker two completed poses ahead of the measurement
                    for q in [q for q in poses[i + 1 :] if q in done][:PREFETCH_POSES]:
                        self._prefetch(q, shots[q], loader)
                    self._measure(p, shots[p], loader, masters)
                else:
                    kind = shots[p][0]["kind"]
                    self._fail(p, kind, "pose not completed (no pose_done record)")
                    self.rejected["pose not completed"] += 1
                if progress:
                    progress(i + 1, len(poses))

    def _prefetch(self, p: int, recs: list[dict[str, Any]], loader: FrameLoader) -> None:
        """Queue pose ``p``'s frames and its board detection for the loader's worker
        (:func:`gonio.capture.pose_measure.detect_board`: the same result as in
        :meth:`_measure`, computed while the previous pose is measured); only the
        frames while the worker is behind (LibRaw's decoding, a slow disk), so that
        this thread detects instead of waiting: the output is the same either way."""
        if loader.behind:
            loader.prefetch(recs)
            return
        try:
            rig = self._rig_of(p, recs)
        except ReductionError:  # _measure says so
            loader.prefetch(recs)
            return
        setup, cam_rep = self.setup, rig[2]

        def detect(results: list[tuple[RawFrame | None, str | None]]) -> Any:
            frames = [fr for fr, _ in results if fr is not None]
            return (setup, detect_board(frames, setup, cam_rep)) if frames else None

        loader.prefetch_pose(recs, detect)

    def _rig_of(self, p: int, recs: list[dict[str, Any]]) -> tuple[Any, ...]:
        """``(light position, light normal, reported camera, wi, wo)`` of pose ``p`` by
        the rig (its journal's last shot), computed once per pose."""
        if p not in self._rig_cache:
            last = recs[-1]
            wi = np.asarray(last.get("wi_achieved") or last.get("wi_requested"), float)
            wo = np.asarray(last.get("wo_achieved") or last.get("wo_requested"), float)
            self._rig_cache[p] = (
                *_rig_pose(self.kin, last.get("joints"), wi, wo, last.get("approach")),
                wi,
                wo,
            )
        return self._rig_cache[p]

    def _checked(
        self, recs: list[dict[str, Any]], results: list[tuple[RawFrame | None, str | None]]
    ) -> list[RawFrame | None]:
        out = []
        for rec, (fr, problem) in zip(recs, results, strict=True):
            if problem is not None:
                self.frame_problems[rec.get("file", "")] = problem
            out.append(fr)
        return out

    def _master_darks(
        self, loader: FrameLoader, shots: dict[int, list[dict]]
    ) -> dict[tuple[float, float], tuple[NDArray[np.float64], int]]:
        """Master darks per (exposure time, ISO): the mean and the number of frames."""
        dark_recs = [rec for recs in shots.values() for rec in recs if rec.get("kind") == "dark"]
        loader.prefetch(dark_recs)
        groups: dict[tuple[float, float], list[RawFrame]] = defaultdict(list)
        for fr in self._checked(dark_recs, loader.results(dark_recs)):
            if fr is not None:
                groups[(round(fr.exposure_time, 9), fr.iso)].append(fr)
        return {k: (np.mean([f.linear for f in v], axis=0), len(v)) for k, v in groups.items()}

    def _fail(self, pose: int, kind: str, reason: str) -> None:
        self.failed_poses.append({"pose": pose, "kind": kind, "reason": reason})

    def _measure(
        self,
        p: int,
        recs: list[dict[str, Any]],
        loader: FrameLoader,
        masters: Mapping[tuple[float, float], tuple[NDArray[np.float64], int]],
    ) -> None:
        kind = recs[0]["kind"]
        frames = []
        dvar = 0.0
        results, ahead = loader.pose_results(recs)
        # the board found in the worker, for this very setup (a profile fit replaces it)
        detected = ahead[1] if ahead is not None and ahead[0] is self.setup else None
        for fr in self._checked(recs, results):
            if fr is None:
                continue
            key = (round(fr.exposure_time, 9), fr.iso)
            if key in masters:
                mdark, nd = masters[key]
                fr = subtract_dark(fr, mdark)
                dvar = self.setup.noise.variance(0.0, iso=fr.iso) / nd
            else:
                self.cal.undarked.add(p)
            if self.cal.flat is not None:
                fr = apply_flat(fr, self.cal.flat.gain)
            frames.append(fr)
        last = recs[-1]
        light_pos, light_n, cam_rep, wi_rep, wo_rep = self._rig_of(p, recs)
        self.pose_inputs[p] = (light_pos, last.get("joints"), last.get("approach"))
        if not frames:
            why = "; ".join(self.frame_problems.get(r.get("file", ""), "?") for r in recs)
            self._fail(p, kind, f"no decodable frame: {why}")
            self.rejected["no decodable frame"] += 1
            if kind == "sample":
                files = tuple(r["file"] for r in recs)
                self.measurements.append(
                    invalid_pose(p, wi_rep, wo_rep, f"no decodable frame: {why}", files)
                )
            return
        setup = self.setup
        if setup.geometry == "auto" and cam_rep is not None:
            if detected is None:
                detected = detect_board(frames, setup, cam_rep)
            if self._rig_beats_board(detected, light_pos, cam_rep, p, last):
                # measure_pose's "rig" mode: the rig's pose, still checked by the board
                setup = setup.replace(geometry="rig")
        try:
            m = measure_pose(
                frames,
                setup,
                light_pos,
                light_n,
                pose=p,
                kind=kind,
                reported_wo=wo_rep,
                reported_camera=cam_rep,
                dark_variance=dvar,
                pixel_mask=self.cal.mask,
                detected=detected,
            )
        except ReductionError as exc:
            self._fail(p, kind, str(exc))
            self.rejected["pose could not be reduced"] += 1
            if kind == "sample":
                names = tuple(f.name for f in frames)
                self.measurements.append(
                    invalid_pose(p, wi_rep, wo_rep, f"pose could not be reduced: {exc}", names)
                )
        else:
            self.measurements.append(m)
            self.cal.light_normal[p] = light_n
            self.cal.exposures[p] = [
                (f.exposure_factor(), f.iso, float(np.min(f.headroom))) for f in frames
            ]
            self.cal.cell_channel = frames[0].cell_channel

    def _geometry_modes(self) -> tuple[Any, Any]:
        """The session's rig modes and the camera calibration's modes (computed once)."""
        if self._modes is None:
            kin_config = getattr(self.kin, "config", None)
            self._modes = (
                session_modes(kin_config, nominal_joint_std_deg=self.setup.nominal_joint_std_deg),
                camera_modes(self.setup.camera_calibration),
            )
        return self._modes

    def _pose_shifts(self, p: int, last: Mapping[str, Any]) -> tuple[Any, Any, Any]:
        """Pose ``p``'s light and camera under every session mode (:meth:`RigShifts.at`)
        at ``last``'s joints and approach.

        One vectorised kinematics evaluation per mode for every pose of the records not
        yet cached (a pose at a time costs 30x more: 90 ms a pose on a calibrated rig).
        An entry is kept with the joints it was computed at and used only for the same
        ones: a pose still being shot when it was cached (an incremental reduction's
        records grow) is computed again."""

        def inputs(rec: Mapping[str, Any]) -> tuple[Any, Any]:
            return rec.get("joints"), rec.get("approach")

        hit = self._shift_cache.get(p)
        if hit is None or hit[0] != inputs(last):
            shots, _ = _shots_by_pose(self.records)
            todo = {
                q: recs[-1]
                for q, recs in shots.items()
                if recs and q not in self._shift_cache and recs[-1].get("joints")
            }
            todo[p] = last
            modes, _ = self._geometry_modes()
            qs = list(todo)
            sh = rig_shifts(
                modes, [todo[q].get("joints") for q in qs], [todo[q].get("approach") for q in qs]
            )
            for k, q in enumerate(qs):
                self._shift_cache[q] = (inputs(todo[q]), sh.at(k))
        return self._shift_cache[p][1]

    def _rig_beats_board(
        self,
        detected: CameraPose | ReductionError,
        light_pos: NDArray[np.float64],
        cam_rep: tuple[NDArray[np.float64], NDArray[np.float64]],
        p: int,
        last: Mapping[str, Any],
    ) -> bool:
        """Whether ``geometry = "auto"`` takes the rig's camera over a trustworthy board
        view at this pose: when the rig's covariance (its calibration's, through the
        kinematics at the pose's joints) moves the pose's directions less than the
        board's own (its corners' reprojection residuals, and the camera calibration's
        modes), by :func:`gonio.capture.budget.direction_variance`.  A board view without
        a covariance, a pose without joints or a rig without modes keeps the board."""
        if not isinstance(detected, CameraPose) or not board_trusted(detected, self.setup):
            return False
        cov = detected.covariance
        if cov is None or not np.all(np.isfinite(cov)) or not last.get("joints"):
            return False
        modes, cmodes = self._geometry_modes()
        if not len(modes):
            return False
        shifts = self._pose_shifts(p, last)
        if not np.all(np.isfinite(shifts[0])):
            return False
        kw = dict(
            session=modes,
            shifts=shifts,
            K=self.setup.K,
            camera_modes=cmodes,
            dist=self.setup.dist,
        )
        roi = self.setup.roi_fraction
        half = (0.5 * roi * self.setup.sample_size[0], 0.5 * roi * self.setup.sample_size[1])
        v_board = direction_variance(detected, light_pos, half, source="board", **kw)
        v_rig = direction_variance(reported_pose(cam_rep), light_pos, half, source="rig", **kw)
        return bool(np.isfinite(v_rig) and np.isfinite(v_board) and v_rig < v_board)

    def samples(self, manifest: Mapping[str, Any]) -> Any:
        """The calibrated samples of the measured sample poses (a BRDFSamples)."""
        from gonio.dataset import BRDFSamples

        samples_m = [m for m in self.measurements if m.kind == "sample"]
        if not samples_m:
            raise SessionError(
                f"{self.session}: no sample pose to reduce"
                + (f" ({self.failed_poses[0]['reason']})" if self.failed_poses else "")
            )
        setup = self.setup
        refs = [m for m in self.measurements if m.kind == "reference"]
        lost = [f for f in self.failed_poses if f.get("kind") == "reference"]
        if not refs and lost:
            # name what became of them (a changed or truncated RAW file), not only that
            # none is left
            shown = "; ".join(f"pose {f['pose']}: {f['reason']}" for f in lost[:3])
            more = f" (and {len(lost) - 3} more)" if len(lost) > 3 else ""
            raise ReductionError(
                f"{self.session}: no reference-target frame could be used, the irradiance is "
                f"unknown: {shown}{more}"
            )
        I, I_var = light_scale(refs, setup)
        self.light = (I, I_var)
        # The calibration scale I is one number per channel shared by every sample: its
        # uncertainty is fully correlated, so it is stored once (calibration_rel_std) for
        # the fitter to add to the parameters it scales, not folded into each sample's
        # sigma (which would let N samples average it down by sqrt(N)).
        drift = self._drift(I)
        light_at = [self._light_at(drift, m.pose, I) for m in samples_m]
        parts = [
            brdf_of(m, It, np.zeros_like(I_var))
            for m, (It, _) in zip(samples_m, light_at, strict=True)
        ]
        # each region's radiance follows its BRDF (brdf = radiance / irradiance)
        rad_scale = [np.ones_like(x[0]) for x in parts]
        if setup.aperture_correction:
            done = [self._aperture_corrected(m, x) for m, x in zip(samples_m, parts, strict=True)]
            parts, rad_scale = [p for p, _ in done], [sc for _, sc in done]
        self._radiometric_terms(samples_m, [u for _, u in light_at])
        brdf = np.concatenate([x[0] for x in parts])
        flags = np.concatenate([m.flags for m in samples_m])
        chart = budget_gradient_chart(setup.gradient_chart, manifest)
        budget, geo = self._budget(samples_m, parts, brdf, flags, chart)
        with np.errstate(invalid="ignore"):
            rel_var = I_var / I**2
            ref_rel = setup.reflectance_std / setup.reflectance
        shared = {
            "reference": ref_rel,
            # what the reference shots' statistics add (I_var holds both)
            "light_scale": np.sqrt(np.maximum(rel_var - ref_rel**2, 0.0)),
        }
        for m in samples_m:
            for rs in m.reasons:
                for r in rs:
                    self.rejected[_reason_key(r)] += 1
        attrs = {
            "session": str(manifest.get("created", "")),
            "software_version": _version(),
            "session_software_version": str(manifest.get("software_version", "")),
            "radiance_units": "camera DN per (s ISO/100 / N^2), vignetting corrected (relative)",
            "irradiance_units": "same camera units x sr (relative); brdf = radiance / irradiance",
            "light_radiance_camera_units": I.tolist(),
            "light_radiance_std": np.sqrt(I_var).tolist(),
            "calibration_rel_std": (np.sqrt(I_var) / I).tolist(),
            "noise_model": json.dumps(
                {
                    "gain": setup.noise.gain,
                    "read_noise": setup.noise.read_noise,
                    "iso": setup.noise.iso,
                }
            ),
            "reference_reflectance": setup.reflectance.tolist(),
            "roi_fraction": setup.roi_fraction,
            "grid": setup.grid if setup.grid_y is None else list(setup.grid_xy),
            # the chart budget["geometry"]'s BRDF gradient was fitted on: a reader that
            # propagates the modes itself (the accuracy harness) must use the same
            "budget_gradient_chart": chart,
            # with stray_gain: the fitter shapes the stray term by the fitted model's
            # directional albedo (gonio.fitting.geometric_uncertainty)
            "stray_fraction": float(setup.stray_fraction),
            "stray_reference_gain": (
                np.full(3, np.nan) if self.cal.g_ref is None else self.cal.g_ref
            ).tolist(),
        }
        # brdf_std: the root sum of squares of the per-sample terms (noise alone before
        # issue 16); the shared terms stay apart (calibration_rel_std, budget attrs)
        brdf_std = np.sqrt(sum(v**2 for v in budget.values()))
        self.budget_summary = self._budget_summary(budget, brdf, flags, shared, geo)
        return BRDFSamples(
            wi=np.concatenate([m.wi for m in samples_m]),
            wo=np.concatenate([m.wo for m in samples_m]),
            brdf=brdf,
            brdf_std=brdf_std,
            flags=flags,
            channels=CHANNELS,
            radiance=np.concatenate(
                [m.radiance * sc for m, sc in zip(samples_m, rad_scale, strict=True)]
            ),
            irradiance=np.concatenate([x[2] for x in parts]),
            frames=np.array([";".join(m.frames) for m in samples_m for _ in range(len(m.flags))]),
            attrs=attrs,
            units={"radiance": RADIANCE_UNITS, "irradiance": IRRADIANCE_UNITS},
            budget=budget,
            shared_budget=shared,
            stray_gain=np.concatenate([self._stray_gain(m) for m in samples_m]),
            **geo["fields"],
        )

    def _stray_gain(self, m: PoseMeasurement) -> NDArray[np.float64]:
        """``G0 / G`` of a pose's regions, (n, C) (NaN where G is not known)."""
        n = len(m.flags)
        g0 = self.cal.g0
        if g0 is None or m.geometry is None or np.shape(m.geometry) != (n, 3):
            return np.full((n, 3), np.nan)
        with np.errstate(invalid="ignore", divide="ignore"):
            g = np.asarray(g0, float) / np.asarray(m.geometry, float)
        return np.where(np.isfinite(g) & (g >= 0), g, np.nan)

    # -- the radiometric calibration (issue 16) ---------------------------------------
    def _radiometric_calibration(
        self,
        loader: FrameLoader,
        shots: dict[int, list[dict]],
        masters: Mapping[tuple[float, float], tuple[NDArray[np.float64], int]],
    ) -> None:
        """The hot pixels of the master darks, the flats' PRNU gain and odd pixels: the
        pixel mask and gain map every pose is measured with."""
        from gonio.capture.pixel_calibration import hot_pixels, prnu_gain

        cal = self.cal
        cal.n_darks = sum(nd for _, nd in masters.values())
        hot = None
        dark_recs = [r for recs in shots.values() for r in recs if r.get("kind") == "dark"]
        first = next(iter(masters.values()), None)
        if first is not None:
            channel = self._channel_map(loader, dark_recs)
            hot = np.zeros(first[0].shape, bool)
            for (_, iso), (mdark, nd) in masters.items():
                floor = float(np.sqrt(self.setup.noise.variance(0.0, iso=iso) / nd))
                # the dark holds the room's ambient image: its photon noise (mean of nd)
                var = functools.partial(_mean_variance, self.setup.noise, iso, nd)
                hot |= hot_pixels(mdark, channel, floor, variance=var)
            cal.n_hot = int(hot.sum())
        flat_recs = [r for recs in shots.values() for r in recs if r.get("kind") == "flat"]
        if flat_recs:
            loader.prefetch(flat_recs)
            frames = [f for f in self._checked(flat_recs, loader.results(flat_recs)) if f]
            if frames:
                key = Counter((round(f.exposure_time, 9), f.iso) for f in frames).most_common(1)
                k0 = key[0][0]
                fs = [f for f in frames if (round(f.exposure_time, 9), f.iso) == k0]
                dark, dvar = None, 0.0
                if k0 in masters:
                    dark = masters[k0][0]
                    dvar = float(self.setup.noise.variance(0.0, iso=k0[1])) / masters[k0][1]
                else:
                    self.warnings.append(
                        f"the flat frames ({fs[0].exposure_time:g} s, ISO {k0[1]:g}) have no "
                        "dark frames at their exposure: the flat field keeps the dark "
                        "signal (shoot [darks] with the [flats])"
                    )
                cal.flat = prnu_gain(
                    [f.linear for f in fs],
                    fs[0].channel,
                    self.setup.K,
                    dark=dark,
                    saturated=np.any([f.saturated for f in fs], axis=0),
                    pixel_variance=lambda S, iso=k0[1]: self.setup.noise.variance(S, iso=iso),
                    dark_variance=dvar,
                    mask=hot,
                )
                cal.n_flats = len(fs)
        mask = hot
        if cal.flat is not None:
            mask = cal.flat.odd if mask is None else (mask | cal.flat.odd)
        cal.mask = mask if mask is not None and mask.any() else None
        cal.n_masked = 0 if cal.mask is None else int(cal.mask.sum())

    def _channel_map(self, loader: FrameLoader, recs: list[dict[str, Any]]) -> NDArray[np.int8]:
        """The CFA channel of each pixel (from one readable frame of ``recs``)."""
        for rec in recs:
            fr, _ = load_frame(self.session, self.setup.signature, rec)
            if fr is not None:
                return fr.channel
        raise ReductionError("no readable dark frame to take the CFA layout from")

    def _fit_profile_first(
        self,
        poses: list[int],
        shots: dict[int, list[dict]],
        done: set[int],
        loader: FrameLoader,
        masters: Mapping[tuple[float, float], tuple[NDArray[np.float64], int]],
    ) -> None:
        """``[light] profile = "fit"``: measure the reference poses once with G as
        configured, fit n from them, and measure the session with that n in G."""
        for p in poses:
            if p in done and shots[p][0]["kind"] == "reference":
                self._measure(p, shots[p], loader, masters)
        refs = [m for m in self.measurements if m.kind == "reference"]
        prof = fit_light_profile(refs, self._cos_psi(refs), self.setup.light_profile_n)
        # applied when it knows n better than the lab's statement does
        if np.isfinite(prof.n_std) and prof.n_std <= self.setup.light_profile_n_std:
            self.setup = self.setup.replace(light_profile_n=prof.n)
            self.cal.profile_applied = True
        else:
            self.warnings.append(
                f"[light] profile = 'fit': the reference regions give n = {prof.n:.3g} +- "
                f"{prof.n_std:.3g}, no better than the stated [light] profile_n_std = "
                f"{self.setup.light_profile_n_std:g}: not applied (n = 0 in G)"
            )
        # measured again below with the fitted n: nothing of this pass is kept
        self.measurements.clear()
        self.failed_poses.clear()
        self.frame_problems.clear()
        self.rejected.clear()

    def _cos_psi(self, ms: list[PoseMeasurement]) -> dict[int, NDArray[np.float64]]:
        """Pose -> (n,) cosine of each region's direction off the light's normal."""
        out = {}
        for m in ms:
            n = self.cal.light_normal.get(m.pose)
            if n is None:
                continue
            n = np.asarray(n, float) / np.linalg.norm(n)
            out[m.pose] = -(m.wi @ n)  # the light emits along -wi towards the region
        return out

    def _drift(self, I: NDArray[np.float64]) -> DriftModel:
        refs = [m for m in self.measurements if m.kind == "reference"]
        order = sorted(self.cal.kinds)
        model = drift_model(refs, self.cal.stamps, order, self.cal.kinds, self.setup, I)
        self.cal.drift = model
        prof = fit_light_profile(refs, self._cos_psi(refs), self.setup.light_profile_n)
        self.cal.profile = prof
        cps = self._cos_psi(refs)
        lc = [np.log(np.clip(cps[m.pose][m.flags == 0], 1e-12, 1.0)) for m in refs if m.pose in cps]
        lc_all = np.concatenate(lc) if lc else np.zeros(0)
        self.cal.cos_psi_ref = float(np.exp(np.mean(lc_all))) if lc_all.size else 1.0
        g0 = []
        for m in refs:
            ok = (m.flags == 0)[:, None] & np.isfinite(m.geometry) & (m.wi[:, 2:3] > 0)
            g0.append(np.where(ok, m.geometry / m.wi[:, 2:3], np.nan))
        self.cal.g0 = np.nanmedian(np.concatenate(g0), axis=0) if g0 else np.full(3, np.nan)
        gains = [
            self.cal.g0 / np.where((m.flags == 0)[:, None], m.geometry, np.nan)
            for m in refs
            if m.geometry is not None
        ]
        with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # no kept reference region: NaN
            self.cal.g_ref = np.nanmean(np.concatenate(gains), axis=0) if gains else None
        return model

    def _light_at(
        self, drift: DriftModel, pose: int, I: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The light's radiance at a sample pose's rig time and the drift term there
        (the pooled ``I`` itself, bit for bit, without repeated reference groups)."""
        seg, t = self.cal.stamps.get(pose, (0, 0.0))
        It, u = drift.at(seg, t)
        if sum(g.segment == seg for g in drift.groups) < 2:
            It = I
        return It, u

    def _radiometric_terms(
        self,
        samples_m: list[PoseMeasurement],
        drift_u: list[NDArray[np.float64]],
    ) -> None:
        """Each sample pose's ``radiometric_rel_std`` (drift, flat, dark, irradiance,
        stray; DEVELOPING.md, "Radiometric budget terms") and the warnings for what the
        session lacks."""
        s, cal = self.setup, self.cal
        prof = cal.profile
        assert prof is not None
        cc = cal.cell_channel
        n_std = prof.n_std if cal.profile_applied else s.light_profile_n_std
        pix_flat = cal.flat.pixel_rel_std if cal.flat is not None else np.full(3, s.prnu)
        self._dark_std = {}
        cos_psi = self._cos_psi(samples_m)
        for m, u_d in zip(samples_m, drift_u, strict=True):
            n = len(m.flags)
            if m.n_pixels is None:  # an invalid pose: no terms to state
                m.radiometric_rel_std = {k: np.full((n, 3), np.nan) for k in _TERMS}
                continue
            # the sites the region's Bayer weights average over (flat, dark offsets)
            n_sites = flat = None
            if cc is not None and m.regions is not None and m.regions.n_regions == n:
                reg = m.regions
                # the pose's pass summed the same weights (measure_pose, with cal.mask):
                # computing them again cost ~8 ms a pose at 1600x1200
                n_sites = m.n_sites
                if n_sites is None or n_sites.shape != (n, 3):
                    n_sites = effective_sites(reg.label, reg.box, cc, n, cal.mask)
                if cal.flat is not None and cal.flat.pixel_rel_map is not None:
                    # each site's gain error at its own flat level (the sample sits where
                    # the flat is brightest)
                    flat = region_flat_rel_std(
                        reg.label, reg.box, cc, n, cal.flat.pixel_rel_map, cal.mask
                    )
            if flat is None:
                flat = flat_rel_std(m.n_pixels, pix_flat, cc, n_sites)
            terms = {
                "drift": np.broadcast_to(u_d, (n, 3)).copy(),
                "flat": flat,
                "dark": np.zeros((n, 3)),
                "irradiance": irradiance_rel_std(
                    cos_psi.get(m.pose, np.ones(n)), cal.cos_psi_ref, n_std
                ),
                "stray": stray_rel_std(m.geometry, cal.g0, s.stray_fraction),
            }
            if m.pose in cal.undarked:
                u_dark = dark_offset_std(
                    m.radiance,
                    m.n_pixels,
                    cal.exposures.get(m.pose, []),
                    s.noise,
                    s.dsnu_e,
                    cc,
                    n_sites,
                )
                with np.errstate(invalid="ignore", divide="ignore"):
                    terms["dark"] = u_dark / np.abs(m.radiance)
                # relative to a black region's 0 it is inf: _budget states it in 1/sr
                self._dark_std[m.pose] = u_dark
            m.radiometric_rel_std = terms
        self.warnings.extend(self._missing_calibration_warnings(samples_m))

    def _missing_calibration_warnings(self, samples_m: list[PoseMeasurement]) -> list[str]:
        s, cal = self.setup, self.cal

        def grown(term: str) -> str:
            kept = [
                m.radiometric_rel_std[term][m.flags == 0]
                for m in samples_m
                if m.radiometric_rel_std
            ]
            v = np.concatenate(kept) if kept else np.zeros((0, 3))
            v = v[np.isfinite(v)]
            if not v.size:
                return "no kept sample to state it for"
            return f"median {100 * np.median(v):.3g} % of the BRDF, largest {100 * np.max(v):.3g} %"

        out = []
        if cal.flat is None:
            out.append(
                "no flat fields in this session ([flats] count = 0): the pixels' gain "
                "(PRNU) and the lens's vignetting beyond cos^4 are not corrected and no "
                "dead pixel is masked; the budget's 'flat' term takes the stated "
                f"[noise] prnu = {s.prnu:g} per pixel: {grown('flat')}"
            )
        if cal.undarked:
            what = (
                "no dark frames" if not cal.n_darks else "frames without a dark at their exposure"
            )
            out.append(
                f"{what} ({len(cal.undarked)} pose(s); [darks] count): the dark offsets "
                "(DSNU, dark current) are not subtracted"
                + (" and no hot pixel is masked" if not cal.n_darks else "")
                + "; the budget's 'dark' term takes the stated "
                f"[noise] dsnu_e = {s.dsnu_e:g} e-: {grown('dark')}"
            )
        segs = {g.segment for g in cal.drift.groups} if cal.drift else set()
        if cal.drift is not None and all(
            sum(g.segment == sg for g in cal.drift.groups) < 2 for sg in segs | {0}
        ):
            out.append(
                "the reference target was shot as one group ([reference] every_poses = 0): "
                "the light's drift is not measured; the budget's 'drift' term is the "
                f"stated [light] drift_rel_std = {100 * s.drift_rel_std:g} % for every sample"
            )
        return out

    @staticmethod
    def _aperture_corrected(
        m: PoseMeasurement, part: tuple[NDArray[np.float64], ...]
    ) -> tuple[tuple[NDArray[np.float64], ...], NDArray[np.float64]]:
        """``brdf_of``'s ``(f, f_std, E, E_var)`` of one pose with each region's aperture
        bias taken out (:mod:`gonio.capture.aperture`): the value at its reported
        direction, the correction's noise added to ``f_std``; and the factor (n, C) the
        region's radiance takes with it (so ``brdf = radiance / irradiance`` stays)."""
        f, f_std, E, E_var = part
        one = np.ones_like(f)
        if m.regions is None or m.n_pixels is None or len(m.flags) != m.regions.n_regions:
            return part, one
        moments = m.regions.extra.get("moments")  # the fused kernel's, the same to the bit
        if moments is None:
            x, y, _ = m.regions.xyz
            moments = region_moments(m.regions.label, x, y, m.regions.n_regions)
        centroid, cov = moments
        bias, bias_std = aperture_bias(centroid, cov, f, f_std, m.flags == 0)
        with np.errstate(invalid="ignore", divide="ignore"):
            scale = np.where(np.isfinite(f) & (f != 0), (f - bias) / f, one)
        return (f - bias, np.sqrt(f_std**2 + bias_std**2), E, E_var), scale

    def _budget(
        self,
        samples_m: list[PoseMeasurement],
        parts: list[tuple[NDArray, ...]],
        brdf: NDArray[np.float64],
        flags: NDArray[np.uint32],
        chart: str = "projected",
    ) -> tuple[dict[str, NDArray[np.float64]], dict[str, Any]]:
        """The per-sample budget terms (N, C) in 1/sr, and the geometric modes' fields.

        ``noise`` is today's std (photon, read, dark subtraction); ``geometry`` the
        marginal std of the modes (:mod:`gonio.capture.budget`) through the local
        gradient of the measured samples, fitted on ``chart``
        (:func:`budget_gradient_chart`); the radiometric terms come from each pose's
        ``radiometric_rel_std`` (relative, (n, C): times f)."""
        modes, cmodes = self._geometry_modes()
        inputs = [self.pose_inputs.get(m.pose) for m in samples_m]
        per_pose, sources, pose_idx = [], [], []
        for k, m in enumerate(samples_m):
            src = m.geometry_source
            n = len(m.flags)
            if m.camera is None or inputs[k] is None or m.kernel == "none":
                src = "none"
            # the shifts _rig_beats_board computed already (rig_shifts is pose by pose
            # the same whatever the other poses of the batch: tested)
            x = inputs[k]
            last = {} if x is None else {"joints": x[1], "approach": x[2]}
            per_pose.append(
                pose_modes(
                    m.wi,
                    m.wo,
                    m.camera,
                    None if inputs[k] is None else inputs[k][0],
                    source=src,
                    session=modes,
                    shifts=self._pose_shifts(m.pose, last),
                    K=self.setup.K,
                    camera_modes=cmodes,
                    dist=self.setup.dist,
                )
            )
            sources += [src] * n
            pose_idx += [m.pose] * n
        gm = np.concatenate(per_pose)
        usable = flags == 0
        grad = local_log_gradient(
            np.concatenate([m.wi for m in samples_m]),
            np.concatenate([m.wo for m in samples_m]),
            brdf
            if self.texels is None
            else texel_levelled(brdf, [len(m.flags) for m in samples_m], usable, self.texels),
            usable,
            isotropic=chart == "isotropic",
        )
        budget: dict[str, NDArray[np.float64]] = {
            "noise": np.concatenate([x[1] for x in parts]),
            "geometry": np.where(np.isfinite(brdf), geometry_std(brdf, grad, gm), np.nan),
        }
        for term in TERMS[2:]:
            rel = [
                np.asarray(getattr(m, "radiometric_rel_std", {}).get(term, 0.0), float)
                for m in samples_m
            ]
            with np.errstate(invalid="ignore"):  # inf x 0: a black region's dark term
                budget[term] = np.concatenate(
                    [
                        np.broadcast_to(r, (len(m.flags), brdf.shape[1]))
                        for r, m in zip(rel, samples_m, strict=True)
                    ]
                ) * np.abs(brdf)
        # a black region (f = 0) of an undarked pose: the offset over its irradiance
        dark_std = self._dark_std
        if dark_std:
            with np.errstate(invalid="ignore", divide="ignore"):
                over_e = np.concatenate(
                    [
                        dark_std[m.pose] / x[2] if m.pose in dark_std else np.zeros_like(x[0])
                        for m, x in zip(samples_m, parts, strict=True)
                    ]
                )
            black = (brdf == 0) & np.isfinite(over_e)
            budget["dark"] = np.where(black, over_e, budget["dark"])
        fields = {
            "geometry_modes": gm,
            "geometry_mode_scope": ["session"] * (len(modes) + len(cmodes))
            + ["pose"] * len(POSE_MODE_NAMES),
            "geometry_mode_names": list(modes.names) + list(cmodes.names) + list(POSE_MODE_NAMES),
            "pose": np.asarray(pose_idx, np.int32),
            "geometry_source": np.asarray(sources, str),
        }
        return budget, {"fields": fields, "modes": modes, "camera_modes": cmodes, "chart": chart}

    @staticmethod
    def _budget_summary(
        budget: Mapping[str, NDArray[np.float64]],
        brdf: NDArray[np.float64],
        flags: NDArray[np.uint32],
        shared: Mapping[str, NDArray[np.float64]],
        geo: Mapping[str, Any],
    ) -> dict[str, Any]:
        modes = geo["modes"]
        src = Counter(geo["fields"]["geometry_source"][flags == 0].tolist())
        return {
            "terms": budget_rows(budget, brdf, flags == 0, shared),
            "session_modes": len(modes),
            "session_mode_source": modes.source,
            "camera_modes": len(geo["camera_modes"]),
            "geometry_source": dict(sorted(src.items())),
            "gradient_chart": geo["chart"],
            "warnings": list(modes.warnings),
        }

    def summary(self, n_samples: int, n_kept: int, path: Path) -> dict[str, Any]:
        """The ``reduction.json`` document."""
        assert self.light is not None
        return {
            "samples": n_samples,
            "kept": n_kept,
            "rejected": dict(sorted(self.rejected.items())),
            "sample_poses": sum(m.kind == "sample" for m in self.measurements),
            "reference_poses": sum(m.kind == "reference" for m in self.measurements),
            "failed_poses": self.failed_poses,
            "frame_problems": dict(sorted(self.frame_problems.items())),
            "light_radiance_camera_units": self.light[0].tolist(),
            "camera_intrinsics": self.setup.intrinsics_source,
            "budget": self.budget_summary,
            "output": path.name,
            "radiometric": self.cal.summary(),
            "warnings": list(self.warnings),
        }


#: The most grazing theta (deg) the retention's headline figure counts.
RETENTION_UP_TO_DEG = 80.0


def retention(
    manifest: Mapping[str, Any],
    measurements: list[PoseMeasurement],
    grid: int | tuple[int, int],
    *,
    up_to_deg: float = RETENTION_UP_TO_DEG,
    band_deg: float = 10.0,
) -> dict[str, Any]:
    """How many of the planned region samples the reduction kept (``reduction.json``
    ``"retention"``), in all and by theta band.

    Every sample pose of the plan (the manifest's ``schedule``; one pose per schedule
    entry, in journal numbering) plans ``grid**2`` (``nx * ny``) region samples, whether
    or not it was shot; a sample is kept when it has no flag.  A pose's band is that of
    the larger of its planned theta_i and theta_o (the more grazing direction): band ``[lo, lo +
    band_deg]`` holds the poses with ``lo < theta <= lo + band_deg`` (the first band
    also theta = 0).  The headline ``planned``, ``kept`` and ``fraction`` count the poses
    up to ``up_to_deg``; bands beyond it are listed but not counted there.

    Parameters
    ----------
    manifest
        The session's manifest (its ``schedule``).
    measurements
        The measured poses (:class:`gonio.capture.pose_measure.PoseMeasurement`); a
        planned pose without one kept nothing.
    grid
        Regions per side of each pose, or ``(nx, ny)``.
    up_to_deg, band_deg
        The headline's largest theta and the bands' width, degrees.

    Returns
    -------
    dict
        ``{"up_to_deg", "band_by", "planned", "kept", "fraction", "bands": [{"theta_deg":
        [lo, hi], "planned", "kept", "fraction"}, ...], "geometry_source": {source:
        kept samples}}``; a fraction is None where nothing was planned.
    """
    gx, gy = (grid, grid) if isinstance(grid, int | np.integer) else grid
    per_pose = int(gx) * int(gy)
    kept_by_pose: dict[int, int] = {}
    sources: Counter[str] = Counter()
    for m in measurements:
        if m.kind == "sample":
            k = int(np.count_nonzero(m.flags == 0))
            kept_by_pose[m.pose] = kept_by_pose.get(m.pose, 0) + k
            if k:
                sources[m.geometry_source] += k
    n_bands = max(1, int(np.ceil(90.0 / band_deg)))
    planned = np.zeros(n_bands, int)
    kept = np.zeros(n_bands, int)
    for p, entry in enumerate(manifest.get("schedule") or []):
        if entry.get("kind") != "sample":
            continue
        theta = max(float(entry["theta_i_deg"]), float(entry["theta_o_deg"]))
        band = min(max(int(np.ceil(theta / band_deg - 1e-9)) - 1, 0), n_bands - 1)
        planned[band] += per_pose
        kept[band] += min(kept_by_pose.get(p, 0), per_pose)

    def frac(k: int, n: int) -> float | None:
        return None if n == 0 else round(k / n, 6)

    inside = np.arange(n_bands) * band_deg < up_to_deg - 1e-9
    bands = [
        {
            "theta_deg": [round(b * band_deg, 6), round(min((b + 1) * band_deg, 90.0), 6)],
            "planned": int(planned[b]),
            "kept": int(kept[b]),
            "fraction": frac(int(kept[b]), int(planned[b])),
        }
        for b in range(n_bands)
        if planned[b] or inside[b]
    ]
    n, k = int(planned[inside].sum()), int(kept[inside].sum())
    return {
        "up_to_deg": up_to_deg,
        "band_by": "max(theta_i, theta_o) of the pose as planned",
        "planned": n,
        "kept": k,
        "fraction": frac(k, n),
        "bands": bands,
        "geometry_source": dict(sorted(sources.items())),
    }


_TERMS = ("drift", "flat", "dark", "irradiance", "stray")


@dataclass
class _Radiometry:
    """The session's radiometric calibration, as the reduction builds it."""

    stamps: dict[int, tuple[int, float]] = field(default_factory=dict)
    kinds: dict[int, str] = field(default_factory=dict)
    flat: Any = None  # gonio.capture.pixel_calibration.FlatField
    mask: NDArray[np.bool_] | None = None
    n_darks: int = 0
    n_flats: int = 0
    n_hot: int = 0
    n_masked: int = 0
    undarked: set[int] = field(default_factory=set)
    light_normal: dict[int, Any] = field(default_factory=dict)
    exposures: dict[int, list[tuple[float, float, float]]] = field(default_factory=dict)
    cell_channel: Any = None
    drift: DriftModel | None = None
    profile: LightProfile | None = None
    profile_applied: bool = False
    g0: NDArray[np.float64] | None = None
    #: (C,) the kept reference regions' mean ``G0 / G``: the room's diffuse light raises
    #: the light scale by ``stray_fraction`` times this (a Lambertian reference)
    g_ref: NDArray[np.float64] | None = None
    cos_psi_ref: float = 1.0

    def summary(self) -> dict[str, Any]:
        """The ``reduction.json["radiometric"]`` block."""
        groups = self.drift.groups if self.drift is not None else []
        return {
            "dark_frames": self.n_darks,
            "flat_frames": self.n_flats,
            "hot_pixels": self.n_hot,
            "masked_pixels": self.n_masked,
            "reference_groups": [
                {
                    "poses": g.poses,
                    "segment": g.segment,
                    "time": g.time,
                    "light_radiance_camera_units": g.I.tolist(),
                    "rel_std": np.sqrt(g.I_rel_var).tolist(),
                }
                for g in groups
            ],
            "light_profile": {
                **(self.profile.to_json() if self.profile is not None else {}),
                "applied": self.profile_applied,
            },
        }


def journal_stamps(records: list[dict[str, Any]]) -> dict[int, tuple[int, float]]:
    """Pose -> ``(segment, time)`` of its shots: the journal segment (a ``start`` record
    opens one: a resume's new bus may restart the rig time) of its last shot, and the
    mean ``rig_time`` of its shots in that segment -- or, in a segment whose shots do not
    all carry ``rig_time`` (journals from before it), the mean position of their records
    in the journal (the drift is then interpolated in journal order)."""
    seg = -1
    per: dict[int, list[tuple[int, float | None, int]]] = defaultdict(list)
    timed: dict[int, bool] = defaultdict(lambda: True)
    for i, r in enumerate(records):
        if r.get("type") == "start":
            seg += 1
        elif r.get("type") == "shot":
            t = r.get("rig_time")
            s = max(seg, 0)
            per[int(r["pose"])].append((s, None if t is None else float(t), i))
            if t is None:
                timed[s] = False
    out = {}
    for p, shots in per.items():
        s = shots[-1][0]
        mine = [x for x in shots if x[0] == s]
        if timed[s]:
            out[p] = (s, float(np.mean([x[1] for x in mine])))
        else:
            out[p] = (s, float(np.mean([x[2] for x in mine])))
    return out


def _write_json(path: Path, doc: Mapping[str, Any]) -> None:
    path.write_text(json.dumps(doc, indent=2, default=str) + "\n", encoding="utf-8")


def budget_gradient_chart(setting: str, manifest: Mapping[str, Any] | None) -> str:
    """The chart the budget's BRDF gradient is fitted on (``"isotropic"`` or
    ``"projected"``, :func:`gonio.capture.budget.local_log_gradient`).

    Parameters
    ----------
    setting
        ``[reduction] gradient_chart``: ``"auto"``, ``"isotropic"`` or ``"projected"``.
    manifest
        The session's manifest (its ``plan``): with ``"auto"``, a plan whose
        ``[reductions] isotropic`` is true declares the material isotropic, and the
        gradient ignores the rotation about the normal; otherwise (or no plan) the
        projected chart, which assumes nothing.

    Returns
    -------
    str
    """
    if setting != "auto":
        return setting
    plan = (manifest or {}).get("plan") or {}
    return "isotropic" if bool((plan.get("reductions") or {}).get("isotropic")) else "projected"


def _kinematics(manifest: Mapping[str, Any]) -> Any | None:
    rig = manifest.get("rig")
    if not rig:
        return None
    try:
        from gonio.rig.config import rig_config_from_dict
        from gonio.rig.kinematics import Kinematics

        return Kinematics(rig_config_from_dict(dict(rig), "manifest.json: rig"))
    except (ImportError, GonioError):
        return None


def _shots_by_pose(records: list[dict[str, Any]]) -> tuple[dict[int, list[dict]], set[int]]:
    shots: dict[int, dict[int, dict]] = defaultdict(dict)
    done: set[int] = set()
    for r in records:
        if r.get("type") == "shot":
            shots[int(r["pose"])][int(r["frame"])] = r  # a redone frame replaces the old
        elif r.get("type") == "pose_done":
            done.add(int(r["pose"]))
    return {p: [fr[k] for k in sorted(fr)] for p, fr in shots.items()}, done


def _mean_variance(
    noise: NoiseModel, iso: float, n: int, signal: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Variance (DN^2) of the mean of ``n`` frames at ISO ``iso`` whose pixels expect
    ``signal`` DN (a master dark's pixel)."""
    return noise.variance(signal, iso=iso) / n


def _reason_key(reason: str) -> str:
    for key in (
        "saturated",
        "signal-to-noise",
        "board not found",
        "camera direction",
        "camera position",
        "no decodable frame",
        "pose could not be reduced",
        "no pixels",
        "region's horizon",
    ):
        if key in reason:
            return {
                "signal-to-noise": "underexposed",
                "camera direction": "geometry mismatch",
                "camera position": "geometry mismatch",
                "region's horizon": "light at the horizon",
            }.get(key, key)
    return reason.split(":")[0][:60]


def _rig_pose(
    kin: Any,
    joints: Mapping[str, float] | None,
    wi: NDArray,
    wo: NDArray,
    approach: Mapping[str, int] | None = None,
):
    """Light position/normal and reported camera (position, world->camera R) of a pose.

    ``approach``: the journal's approach signs of the joints (None in journals written
    before they were recorded: unknown)."""
    if kin is not None and joints:
        try:
            appr = {k: int(v) for k, v in approach.items()} if approach else None
            rp = kin.poses({k: float(v) for k, v in joints.items()}, appr)
            return (
                np.asarray(rp.light_position, float),
                np.asarray(rp.light_normal, float),
                (np.asarray(rp.camera_position, float), np.asarray(rp.camera_rotation, float).T),
            )
        except GonioError:
            pass
    raise ReductionError(
        "the light's position is unknown: the manifest has no rig configuration with "
        "kinematics for the journal's joint angles"
    )


def _version() -> str:
    try:
        from gonio import __version__

        return str(__version__)
    except ImportError:  # pragma: no cover
        return "unknown"


# An adaptive session reduces as it goes (issue 17): the class lives in its own module,
# on top of _PoseRun's per-pose path.
from gonio.capture.adaptive_reduce import IncrementalReduction, with_round_steps  # noqa: E402
