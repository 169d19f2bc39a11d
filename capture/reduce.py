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

import json
import os
from collections import Counter, defaultdict
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gonio.capture.budget import (
    POSE_MODE_NAMES,
    TERMS,
    budget_rows,
    camera_modes,
    geometry_std,
    local_log_gradient,
    pose_modes,
    rig_shifts,
    session_modes,
)
from gonio.capture.frame_loader import PREFETCH_POSES, FrameLoader, default_threads, load_frame
from gonio.capture.noise import NoiseModel
from gonio.capture.output_set import output_set
from gonio.capture.pose_measure import PoseMeasurement, invalid_pose, measure_pose
from gonio.capture.radiometric import brdf_of, light_scale
from gonio.capture.raw import CHANNELS, RawFrame, subtract_dark
from gonio.capture.reduction_config import (
    CONFIG_FILE,
    NOISE_FILE,
    ReductionSetup,
    resolve_setup,
)
from gonio.capture.samples_plot import plot_samples
from gonio.dataset import save_samples
from gonio.errors import GonioError, ReductionError, SessionError
from gonio.locks import hold_lock

__all__ = [
    "CONFIG_FILE",
    "NOISE_FILE",
    "PLOT_FILE",
    "RADIANCE_UNITS",
    "IRRADIANCE_UNITS",
    "SAMPLES_FILE",
    "SUMMARY_FILE",
    "ReductionResult",
    "ReductionSetup",
    "default_threads",
    "output_lock",
    "reduce_session",
    "resolve_setup",
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
    """

    path: Path
    n_samples: int
    n_kept: int
    rejected: dict[str, int]
    summary: dict[str, Any]
    plot: Path | None


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

    Returns
    -------
    ReductionResult

    Raises
    ------
    SessionError
        Not a session directory, no ``reduction.toml``, or nothing to reduce.
    ReductionError
        No usable reference frames (the irradiance cannot be calibrated).
    gonio.locks.LockedError
        Another process is writing the same output (nothing is written).
    """
    from gonio.capture.journal import read_journal, session_file
    from gonio.capture.manifest import load_manifest, refuse_calibration_session

    session = Path(session_dir)
    manifest = load_manifest(session)
    refuse_calibration_session(session, manifest)
    records = read_journal(session / "journal.jsonl")
    for rec in records:  # a journal naming a file outside the session is refused outright
        if rec.get("type") == "shot":
            session_file(session, rec)
    if setup is None:
        setup = resolve_setup(session, manifest, noise)
    elif noise is not None:
        setup = setup.replace(noise=noise)
    path = Path(out) if out is not None else session / SAMPLES_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    with hold_lock(output_lock(path), f"output {path}"):
        run = _PoseRun(session, setup, _kinematics(manifest), records)
        run.measure_all(default_threads() if threads is None else max(1, int(threads)), progress)
        samples = run.samples(manifest)
        n_kept = int(samples.valid.sum())
        summary = run.summary(len(samples), n_kept, path)
        # One set: a kill leaves the old samples, summary and plot, or the new ones.
        with output_set(path, (path.name, SUMMARY_FILE, PLOT_FILE)) as stage:
            save_samples(stage / path.name, samples)
            _write_json(stage / SUMMARY_FILE, summary)
            if plot:
                plot_samples(samples, stage / PLOT_FILE)
        plot_path = path.with_name(PLOT_FILE) if plot else None
    return ReductionResult(path, len(samples), n_kept, dict(run.rejected), summary, plot_path)


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
    #: pose -> (light position, journaled joints, approach): what the budget's geometry
    #: modes move (:mod:`gonio.capture.budget`)
    pose_inputs: dict[int, tuple[Any, Any, Any]] = field(default_factory=dict)
    budget_summary: dict[str, Any] = field(default_factory=dict)

    def measure_all(self, threads: int, progress: Callable[[int, int], None] | None) -> None:
        """Decode and measure every sample and reference pose, in journal order."""
        shots, done = _shots_by_pose(self.records)
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
            poses = sorted(
                p
                for p, recs in shots.items()
                if recs and recs[0].get("kind") in ("sample", "reference")
            )
            for i, p in enumerate(poses):
                if p in done:
                    # keep the worker two completed poses ahead of the measurement
                    for q in [q for q in poses[i + 1 :] if q in done][:PREFETCH_POSES]:
                        loader.prefetch(shots[q])
                    self._measure(p, shots[p], loader, masters)
                else:
                    kind = shots[p][0]["kind"]
                    self._fail(p, kind, "pose not completed (no pose_done record)")
                    self.rejected["pose not completed"] += 1
                if progress:
                    progress(i + 1, len(poses))

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
        for fr in self._checked(recs, loader.results(recs)):
            if fr is None:
                continue
            key = (round(fr.exposure_time, 9), fr.iso)
            if key in masters:
                mdark, nd = masters[key]
                fr = subtract_dark(fr, mdark)
                dvar = self.setup.noise.variance(0.0, iso=fr.iso) / nd
            frames.append(fr)
        last = recs[-1]
        wi_rep = np.asarray(last.get("wi_achieved") or last.get("wi_requested"), float)
        wo_rep = np.asarray(last.get("wo_achieved") or last.get("wo_requested"), float)
        light_pos, light_n, cam_rep = _rig_pose(
            self.kin, last.get("joints"), wi_rep, wo_rep, last.get("approach")
        )
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
        try:
            m = measure_pose(
                frames,
                self.setup,
                light_pos,
                light_n,
                pose=p,
                kind=kind,
                reported_wo=wo_rep,
                reported_camera=cam_rep,
                dark_variance=dvar,
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
        I, I_var = light_scale([m for m in self.measurements if m.kind == "reference"], setup)
        self.light = (I, I_var)
        # The calibration scale I is one number per channel shared by every sample: its
        # uncertainty is fully correlated, so it is stored once (calibration_rel_std) for
        # the fitter to add to the parameters it scales, not folded into each sample's
        # sigma (which would let N samples average it down by sqrt(N)).
        parts = [brdf_of(m, I, np.zeros_like(I_var)) for m in samples_m]
        brdf = np.concatenate([x[0] for x in parts])
        flags = np.concatenate([m.flags for m in samples_m])
        budget, geo = self._budget(samples_m, parts, brdf, flags)
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
            "grid": setup.grid,
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
            radiance=np.concatenate([m.radiance for m in samples_m]),
            irradiance=np.concatenate([x[2] for x in parts]),
            frames=np.array([";".join(m.frames) for m in samples_m for _ in range(len(m.flags))]),
            attrs=attrs,
            units={"radiance": RADIANCE_UNITS, "irradiance": IRRADIANCE_UNITS},
            budget=budget,
            shared_budget=shared,
            **geo["fields"],
        )

    def _budget(
        self,
        samples_m: list[PoseMeasurement],
        parts: list[tuple[NDArray, ...]],
        brdf: NDArray[np.float64],
        flags: NDArray[np.uint32],
    ) -> tuple[dict[str, NDArray[np.float64]], dict[str, Any]]:
        """The per-sample budget terms (N, C) in 1/sr, and the geometric modes' fields.

        ``noise`` is today's std (photon, read, dark subtraction); ``geometry`` the
        marginal std of the modes (:mod:`gonio.capture.budget`) through the local
        gradient of the measured samples; the radiometric terms come from each pose's
        ``radiometric_rel_std`` (relative, (n, C): times f)."""
        kin_config = getattr(self.kin, "config", None)
        modes = session_modes(kin_config, nominal_joint_std_deg=self.setup.nominal_joint_std_deg)
        cmodes = camera_modes(self.setup.camera_calibration)
        inputs = [self.pose_inputs.get(m.pose) for m in samples_m]
        shifts = rig_shifts(
            modes,
            [None if x is None else x[1] for x in inputs],
            [None if x is None else x[2] for x in inputs],
        )
        per_pose, sources, pose_idx = [], [], []
        for k, m in enumerate(samples_m):
            src = getattr(m, "geometry_source", None) or _geometry_source(m)
            n = len(m.flags)
            if m.camera is None or inputs[k] is None or m.kernel == "none":
                src = "none"
            per_pose.append(
                pose_modes(
                    m.wi,
                    m.wo,
                    m.camera,
                    None if inputs[k] is None else inputs[k][0],
                    source=src,
                    session=modes,
                    shifts=shifts.at(k),
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
            brdf,
            usable,
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
            budget[term] = np.concatenate(
                [
                    np.broadcast_to(r, (len(m.flags), brdf.shape[1]))
                    for r, m in zip(rel, samples_m, strict=True)
                ]
            ) * np.abs(brdf)
        fields = {
            "geometry_modes": gm,
            "geometry_mode_scope": ["session"] * (len(modes) + len(cmodes))
            + ["pose"] * len(POSE_MODE_NAMES),
            "geometry_mode_names": list(modes.names) + list(cmodes.names) + list(POSE_MODE_NAMES),
            "pose": np.asarray(pose_idx, np.int32),
            "geometry_source": np.asarray(sources, str),
        }
        return budget, {"fields": fields, "modes": modes, "camera_modes": cmodes}

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
            "budget": self.budget_summary,
            "output": path.name,
        }


def _write_json(path: Path, doc: Mapping[str, Any]) -> None:
    path.write_text(json.dumps(doc, indent=2, default=str) + "\n", encoding="utf-8")


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


def _geometry_source(m: PoseMeasurement) -> str:
    """Where a pose's camera came from when the measurement does not say: the board when
    its pose has a covariance (solved from corners), else the rig's report."""
    if m.camera is None:
        return "none"
    return "board" if getattr(m.camera, "covariance", None) is not None else "rig"


def _shots_by_pose(records: list[dict[str, Any]]) -> tuple[dict[int, list[dict]], set[int]]:
    shots: dict[int, dict[int, dict]] = defaultdict(dict)
    done: set[int] = set()
    for r in records:
        if r.get("type") == "shot":
            shots[int(r["pose"])][int(r["frame"])] = r  # a redone frame replaces the old
        elif r.get("type") == "pose_done":
            done.add(int(r["pose"]))
    return {p: [fr[k] for k in sorted(fr)] for p, fr in shots.items()}, done


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
    ):
        if key in reason:
            return {
                "signal-to-noise": "underexposed",
                "camera direction": "geometry mismatch",
                "camera position": "geometry mismatch",
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
