"""Camera intrinsics and lens distortion from ChArUco views (``gonio calibrate camera``).

The views are the holder's board seen from many directions: the RAW frames of a
calibration session (the best-exposed frame of each pose) or a folder of images.  The
board is found with the reduction's own detector (:mod:`gonio.capture.fiducials`), and
``cv2.calibrateCameraExtended`` solves the camera matrix and five Brown-Conrady terms
(k1 k2 p1 p2 k3) with a standard deviation for each.  Views with too few corners, or whose
reprojection error is an outlier, are left out with the reason and the solve repeated.

Pixel coordinates follow OpenCV: pixel centres at integer coordinates.

About OpenCV's standard deviations: they are the square roots of the diagonal of
``s^2 (J^T J)^-1``, with ``s^2 = sum(e^2) / (2 N - p)`` the residual variance per
coordinate (N corners, p parameters: intrinsics and six per view), i.e. the usual
least-squares covariance under independent Gaussian corner noise.  The test-suite checks
them against the spread of the estimates over seeds (``tests/capture/test_camera_calibration.py``).
Its RMS (``rms_px``) is ``sqrt(sum |e|^2 / N)``: the 2-D error per corner, so for corner
noise of sigma px per coordinate it is about ``sigma sqrt(2 (1 - p / (2 N)))``.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated, Any

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, field_validator

from gonio.capture.fiducials import (
    BoardSpec,
    _corner_spacing,
    _detect_corners,
    binned_grey_uint8,
    grey_from_mosaic,
    grey_image,
    to_uint8,
)
from gonio.capture.raw import RawFrame, read_raw
from gonio.errors import FileFormatError, GonioError, ReductionError

__all__ = [
    "CalibrationView",
    "CameraCalibration",
    "CameraCalibrationError",
    "CameraMismatch",
    "RejectedView",
    "DEFAULT_FLAGS",
    "IMAGE_SUFFIXES",
    "calibrate_camera",
    "camera_digest",
    "camera_identity",
    "check_camera",
    "detect_view",
    "detect_views",
    "load_camera_calibration",
    "views_from_folder",
    "views_from_session",
    "write_camera_calibration",
]

#: File suffixes a folder of calibration images may hold (RAW through LibRaw, the rest
#: through OpenCV's image reader).
RAW_SUFFIXES = (".dng", ".cr2", ".cr3", ".nef", ".arw", ".raf", ".orf", ".rw2", ".pef")
IMAGE_SUFFIXES = (*RAW_SUFFIXES, ".png", ".jpg", ".jpeg", ".tif", ".tiff")

#: Four distortion terms (k1 k2 p1 p2; k3 held at 0), free aspect ratio and principal
#: point.  The rig's camera always aims at the holder, so the board's corners form a ring
#: around the image centre: k3 is then barely separable from k1 and k2 (over 30 simulated
#: rigs its error was 10^3 times its reported std, and it spoiled k1, k2), so it is fixed
#: as usual for a non-wide lens (``cv2.CALIB_FIX_K3``; pass ``flags=0`` to solve it).
DEFAULT_FLAGS = cv2.CALIB_FIX_K3

#: ``stdDeviationsIntrinsics`` order (OpenCV): fx fy cx cy k1 k2 p1 p2 k3 ...
INTRINSIC_NAMES = ("fx", "fy", "cx", "cy")
DIST_NAMES = ("k1", "k2", "p1", "p2", "k3")


class CameraCalibrationError(GonioError):
    """A camera calibration that cannot be made from the views given."""


class CameraMismatch(GonioError):
    """A camera calibration file made for another camera than the one in use."""


@dataclass(frozen=True)
class CalibrationView:
    """The board as one image shows it.

    Attributes
    ----------
    label
        Where it came from (file name or ``"pose 3"``), for messages.
    ids
        (n,) ChArUco corner ids.
    image_points
        (n, 2) detected corners, px (OpenCV convention).
    object_points
        (n, 3) the same corners in the board frame, m (z = 0).
    image_size
        ``(width, height)`` of the image, px.
    problem
        Why no corners were found (None when the board was detected).
    """

    label: str
    ids: NDArray[np.int32]
    image_points: NDArray[np.float64]
    object_points: NDArray[np.float64]
    image_size: tuple[int, int]
    problem: str | None = None

    @property
    def n_corners(self) -> int:
        """Number of corners detected."""
        return int(len(self.ids))


@dataclass(frozen=True)
class RejectedView:
    """A view left out of the solve, and why."""

    label: str
    reason: str


@dataclass(frozen=True)
class CameraCalibration:
    """The result of :func:`calibrate_camera`.

    Attributes
    ----------
    K, K_std
        (3, 3) camera matrix, px (OpenCV: pixel centres at integers); (4,) standard
        deviations of fx, fy, cx, cy, px.
    dist, dist_std
        (5,) k1 k2 p1 p2 k3 (OpenCV Brown-Conrady on normalised coordinates) and their
        standard deviations.
    rms_px
        Reprojection RMS over all corners used, px (2-D error per corner).
    image_size
        ``(width, height)``, px.
    used
        Labels of the views in the final solve.
    view_errors
        Label -> per-view reprojection RMS, px (views used).
    rejected
        Views left out, with the reason.
    n_points
        Corners in the final solve.
    covariance
        (9, 9) covariance of ``fx fy cx cy k1 k2 p1 p2 k3`` (the views' poses eliminated;
        rows and columns of held parameters 0), from the solution's Jacobian with
        OpenCV's residual variance: its diagonal is ``K_std``, ``dist_std`` squared.  The
        terms are strongly correlated (k1 with k2, f with k1), so a later solve that
        takes this calibration as a prior needs the whole matrix, not the diagonal.
    image_points
        Label -> (n, 2) corners of each view used (for coverage plots).
    """

    K: NDArray[np.float64]
    K_std: NDArray[np.float64]
    dist: NDArray[np.float64]
    dist_std: NDArray[np.float64]
    rms_px: float
    image_size: tuple[int, int]
    used: tuple[str, ...]
    view_errors: dict[str, float]
    rejected: tuple[RejectedView, ...]
    n_points: int
    image_points: dict[str, NDArray[np.float64]] = field(default_factory=dict, repr=False)
    covariance: NDArray[np.float64] | None = field(default=None, repr=False)

    @property
    def parameters(self) -> dict[str, tuple[float, float]]:
        """Name -> (value, std) for fx fy cx cy k1 k2 p1 p2 k3."""
        vals = (self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2], *self.dist)
        stds = (*self.K_std, *self.dist_std)
        names = INTRINSIC_NAMES + DIST_NAMES
        return {n: (float(v), float(s)) for n, v, s in zip(names, vals, stds, strict=True)}


# -- detection ----------------------------------------------------------------------------
def _empty_view(label: str, size: tuple[int, int], problem: str) -> CalibrationView:
    return CalibrationView(
        label, np.zeros(0, np.int32), np.zeros((0, 2)), np.zeros((0, 3)), size, problem
    )


def _corners_in_frame(
    frame: RawFrame, board: BoardSpec, name: str, min_corners: int, max_width: int
) -> tuple[NDArray[np.float64], NDArray[np.int32]]:
    # Detected as the reduction detects them (fiducials); a large mosaic is binned for
    # the markers, then each corner refined on the full-resolution grey image.
    H, W = frame.shape
    factor = 1
    while W / factor > max_width:
        factor *= 2
    if factor == 1:
        return _detect_corners(grey_from_mosaic(frame), board, name, min_corners)
    corners, ids = _detect_corners(binned_grey_uint8(frame, factor), board, name, min_corners)
    full = corners * factor + (factor - 1) / 2.0
    half_win = int(np.clip(round(0.12 * _corner_spacing(full, ids, board)), 3, 15))
    pts = full.reshape(-1, 1, 2).astype(np.float32)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 1e-3)
    cv2.cornerSubPix(grey_image(frame, 1), pts, (half_win, half_win), (-1, -1), crit)
    return pts.reshape(-1, 2).astype(np.float64), ids


def detect_view(
    image: RawFrame | NDArray,
    board: BoardSpec,
    *,
    label: str | None = None,
    min_corners: int = 4,
    max_width: int = 1600,
) -> CalibrationView:
    """Detect the ChArUco board in one image.

    Parameters
    ----------
    image
        A decoded RAW frame (its channel-equalised mosaic is searched) or a grey or BGR
        image (uint8, or float scaled to its 99.5th percentile).
    board
        The board printed on the holder.
    label
        Name for messages (default: the frame's name).
    min_corners
        Fewest corners counted as a detection.
    max_width
        Mosaics wider than this are searched binned, then refined at full resolution.

    Returns
    -------
    CalibrationView
        With ``problem`` set (and no corners) when the board was not found.
    """
    name = label or (image.name if isinstance(image, RawFrame) else "image")
    try:
        if isinstance(image, RawFrame):
            H, W = image.shape
            corners, ids = _corners_in_frame(image, board, name, min_corners, max_width)
        else:
            img = np.asarray(image)
            if img.ndim == 3:
                img = (
                    cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.dtype == np.uint8 else img.mean(2)
                )
            if img.dtype != np.uint8:
                img = to_uint8(img.astype(np.float32), name)
            H, W = img.shape
            corners, ids = _detect_corners(img, board, name, min_corners)
    except ReductionError as exc:
        size = image.shape[::-1] if isinstance(image, RawFrame) else np.shape(image)[1::-1]
        return _empty_view(name, (int(size[0]), int(size[1])), str(exc))
    obj = np.asarray(board.cv_board().getChessboardCorners(), np.float64)[ids]
    return CalibrationView(name, ids, corners, obj, (int(W), int(H)))


def detect_views(
    images: Iterable[RawFrame | NDArray | tuple[str, RawFrame | NDArray]],
    board: BoardSpec,
    *,
    min_corners: int = 4,
    source: str = "the images",
) -> list[CalibrationView]:
    """Detect the board in every image (see :func:`detect_view`).

    ``images`` holds frames or arrays, or ``(label, image)`` pairs.  Views where the board
    was not found are kept, with ``problem`` saying why, so the calibration can report
    them.

    Raises
    ------
    CameraCalibrationError
        No images, or the board was found in none of them (``source`` named).
    """
    views = []
    for item in images:
        label, img = item if isinstance(item, tuple) else (None, item)
        views.append(detect_view(img, board, label=label, min_corners=min_corners))
    if not views:
        raise CameraCalibrationError(f"{source}: no images to calibrate from")
    if all(v.problem is not None for v in views):
        raise CameraCalibrationError(
            f"{source}: the ChArUco board ({board.squares_x}x{board.squares_y} squares, "
            f"{board.dictionary}) was not found in any of the {len(views)} images "
            f"(first: {views[0].problem})"
        )
    return views


def views_from_folder(
    folder: str | os.PathLike, board: BoardSpec, *, min_corners: int = 4
) -> list[CalibrationView]:
    """Detect the board in every RAW/DNG/PNG/JPEG/TIFF image of a folder (name order).

    Raises
    ------
    CameraCalibrationError
        No image in the folder, or the board in none of them.
    FileFormatError
        An image that cannot be read.
    """
    folder = Path(folder)
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise CameraCalibrationError(
            f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)}) to calibrate from"
        )

    def load(p: Path) -> tuple[str, RawFrame | NDArray]:
        if p.suffix.lower() in RAW_SUFFIXES:
            return p.name, read_raw(p, name=p.name)
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise FileFormatError(p, "not an image OpenCV can read")
        return p.name, img

    return detect_views(
        (load(p) for p in files), board, min_corners=min_corners, source=str(folder)
    )


def views_from_session(
    session_dir: str | os.PathLike,
    board: BoardSpec,
    *,
    kinds: Sequence[str] = ("sample", "mirror"),
    min_corners: int = 4,
) -> list[CalibrationView]:
    """One view per pose of a session: its best-exposed frame (journal order).

    Frames are read through the journal (byte count and digest checked, paths kept
    inside the session); a missing or damaged frame becomes a view with a problem.
    """
    from gonio.capture.frame_loader import load_frame
    from gonio.capture.journal import latest_shots, read_journal
    from gonio.capture.pose_measure import _detection_frame

    session_dir = Path(session_dir)
    journal = session_dir / "journal.jsonl"
    if not journal.is_file():
        raise CameraCalibrationError(f"{session_dir}: not a session (no journal.jsonl)")
    by_pose: dict[int, list[Mapping[str, Any]]] = {}
    for (pose, _frame), rec in sorted(latest_shots(read_journal(journal)).items()):
        if rec.get("kind", "sample") in kinds:
            by_pose.setdefault(pose, []).append(rec)
    views: list[CalibrationView] = []
    for pose, recs in by_pose.items():
        frames, problems = [], []
        for rec in recs:
            fr, problem = load_frame(session_dir, None, rec)
            if fr is None:
                problems.append(problem)
            else:
                frames.append(fr)
        label = f"pose {pose}"
        if not frames:
            views.append(_empty_view(label, (0, 0), "; ".join(p or "" for p in problems)))
            continue
        views.append(
            detect_view(_detection_frame(frames), board, label=label, min_corners=min_corners)
        )
    if not views:
        raise CameraCalibrationError(f"{session_dir}: the journal has no frames of the board")
    if all(v.problem is not None for v in views):
        raise CameraCalibrationError(
            f"{session_dir}: the ChArUco board was not found in any of its {len(views)} "
            f"poses (first: {views[0].problem})"
        )
    return views


# -- solve ---------------------------------------------------------------------------------
def _solve(views: list[CalibrationView], image_size: tuple[int, int], flags: int) -> Any:
    obj = [v.object_points.astype(np.float32).reshape(-1, 1, 3) for v in views]
    img = [v.image_points.astype(np.float32).reshape(-1, 1, 2) for v in views]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    return cv2.calibrateCameraExtended(
        obj, img, tuple(int(x) for x in image_size), None, np.zeros(5), flags=flags, criteria=crit
    )


def _intrinsics_covariance(
    views: list[CalibrationView], K: Any, dist: Any, rvecs: Any, tvecs: Any, free: NDArray
) -> NDArray[np.float64]:
    """(9, 9) covariance of fx fy cx cy k1 k2 p1 p2 k3: ``s^2`` times the intrinsics'
    block of ``(J^T J)^-1`` (Schur complement over the views' poses), ``s^2`` OpenCV's
    ``sum e^2 / (2 N - p)``; ``free`` is the mask of the solved intrinsics."""
    K = np.asarray(K, float)
    d = np.asarray(dist, float).ravel()[:5]
    nfree = int(free.sum())
    normal = np.zeros((nfree, nfree))
    sse, n = 0.0, 0
    for v, rv, tv in zip(views, rvecs, tvecs, strict=True):
        obj = v.object_points.reshape(-1, 1, 3).astype(np.float64)
        uv, jac = cv2.projectPoints(obj, rv, tv, K, d)
        e = uv.reshape(-1, 2) - v.image_points
        sse += float(np.sum(e**2))
        n += len(e)
        # projectPoints' columns: rvec 3, tvec 3, fx fy, cx cy, the five distortion terms
        ext, intr = jac[:, :6], jac[:, 6:15][:, free]
        a, b, c = intr.T @ intr, intr.T @ ext, ext.T @ ext
        normal += a - b @ np.linalg.solve(c, b.T)
    s2 = sse / max(2 * n - nfree - 6 * len(views), 1)
    cov = np.zeros((9, 9))
    cov[np.ix_(free, free)] = s2 * np.linalg.inv(normal)
    return cov


def _collinear(v: CalibrationView) -> bool:
    # corners on one line (one row of the board) give no homography
    p = v.object_points[:, :2] - v.object_points[:, :2].mean(0)
    s = np.linalg.svd(p, compute_uv=False)
    return bool(s[-1] <= 1e-9 * max(s[0], 1e-300))


def calibrate_camera(
    views: Sequence[CalibrationView],
    image_size: tuple[int, int] | None = None,
    *,
    min_views: int = 6,
    min_corners: int = 8,
    flags: int = DEFAULT_FLAGS,
    outlier_factor: float = 3.0,
    outlier_floor_px: float = 1.0,
    source: str | None = None,
) -> CameraCalibration:
    """Solve the camera matrix and distortion from board views.

    Parameters
    ----------
    views
        From :func:`detect_views` (views with a ``problem`` are reported as rejected).
    image_size
        ``(width, height)``, px; by default the views' own (they must agree).
    min_views
        Fewest views the solve accepts (after rejections).
    min_corners
        Views with fewer corners are rejected (a homography needs 4; 8 keep it stable).
    flags
        ``cv2.CALIB_*`` flags; the default solves fx, fy, cx, cy and k1 k2 p1 p2 k3.
    outlier_factor, outlier_floor_px
        A view whose reprojection RMS exceeds both ``outlier_factor`` x the median view's
        and ``outlier_floor_px`` is rejected and the solve repeated.
    source
        Where the views came from (a session or folder), to name in errors.

    Returns
    -------
    CameraCalibration

    Raises
    ------
    CameraCalibrationError
        Fewer than ``min_views`` usable views ("N views with a board, need at least M"),
        images of different sizes, or a solve OpenCV cannot make (degenerate views).
    """
    where = f"{source}: " if source else ""
    rejected: list[RejectedView] = []
    usable: list[CalibrationView] = []
    sizes = {v.image_size for v in views if v.problem is None}
    if image_size is None:
        if len(sizes) > 1:
            raise CameraCalibrationError(
                f"{where}the views have different image sizes {sorted(sizes)}; calibrate one "
                "camera and resolution at a time"
            )
        image_size = next(iter(sizes), (0, 0))
    image_size = (int(image_size[0]), int(image_size[1]))
    for v in views:
        if v.problem is not None:
            rejected.append(RejectedView(v.label, v.problem))
        elif v.image_size != image_size:
            rejected.append(
                RejectedView(v.label, f"image is {v.image_size[0]}x{v.image_size[1]}, not "
                             f"{image_size[0]}x{image_size[1]}")
            )  # fmt: skip
        elif v.n_corners < min_corners:
            rejected.append(
                RejectedView(v.label, f"{v.n_corners} corners, need at least {min_corners}")
            )
        elif _collinear(v):
            rejected.append(RejectedView(v.label, "its corners lie on one line (degenerate)"))
        else:
            usable.append(v)
    n_board = sum(v.problem is None for v in views)
    while True:
        if len(usable) < min_views:
            raise CameraCalibrationError(
                f"{where}{len(usable)} views with a board, need at least {min_views}"
                + (f" ({n_board} with a board found, {len(rejected)} rejected: "
                   + "; ".join(f"{r.label}: {r.reason}" for r in rejected[:5]) + ")"
                   if rejected else "")
            )  # fmt: skip
        try:
            rms, K, dist, rvecs, tvecs, std_in, _std_ex, per_view = _solve(
                usable, image_size, flags
            )
        except cv2.error as exc:
            raise CameraCalibrationError(
                f"{where}OpenCV could not calibrate from {len(usable)} views (degenerate views: "
                f"too few distinct board orientations?): {exc.msg.strip()}"
            ) from None
        errs = np.asarray(per_view, float).ravel()
        std_in = np.asarray(std_in, float).ravel()
        if not (np.isfinite(K).all() and np.isfinite(dist).all() and np.isfinite(rms)):
            raise CameraCalibrationError(
                f"{where}the calibration from {len(usable)} views did not converge (all views "
                "degenerate: the board must be seen at several different tilts)"
            )
        if not np.isfinite(std_in[:9]).all():
            raise CameraCalibrationError(
                f"{where}the calibration from {len(usable)} views leaves some parameters "
                "undetermined (standard deviations not finite): show the board at more "
                "different tilts and positions in the image"
            )
        med = float(np.median(errs))
        bad = [i for i, e in enumerate(errs) if e > outlier_factor * med and e > outlier_floor_px]
        if not bad:
            break
        for i in sorted(bad, reverse=True):
            rejected.append(
                RejectedView(
                    usable[i].label,
                    f"reprojection RMS {errs[i]:.2f} px is more than {outlier_factor:g}x "
                    f"the median view's ({med:.2f} px)",
                )
            )
            del usable[i]
    return CameraCalibration(
        K=np.asarray(K, float),
        K_std=std_in[:4].copy(),
        dist=np.asarray(dist, float).ravel()[:5].copy(),
        dist_std=std_in[4:9].copy(),
        rms_px=float(rms),
        image_size=image_size,
        used=tuple(v.label for v in usable),
        view_errors={v.label: float(e) for v, e in zip(usable, errs, strict=True)},
        rejected=tuple(rejected),
        n_points=int(sum(v.n_corners for v in usable)),
        image_points={v.label: v.image_points for v in usable},
        covariance=_intrinsics_covariance(usable, K, dist, rvecs, tvecs, std_in[:9] > 0),
    )


# -- identity ------------------------------------------------------------------------------
def camera_identity(info: Any, image_size: tuple[int, int] | None = None) -> dict[str, Any]:
    """``{backend, model, serial, resolution}`` of a camera.

    ``info`` is a :class:`gonio.devices.CameraInfo`, its JSON (a session manifest's
    ``camera``) or a mapping already in this form.  The serial is the camera's
    ``serial`` setting (None when it reports none); the resolution its ``resolution``
    setting, else ``image_size``.
    """
    from gonio.capture.reduction_config import identity_of

    # one identity for the file written here and the check the reduction makes
    return identity_of(info.to_json() if hasattr(info, "to_json") else dict(info), image_size)


def camera_digest(identity: Mapping[str, Any]) -> str:
    """``"sha256:<hex>"`` of the canonical JSON of a camera's backend, model, serial and
    resolution (sorted keys, no spaces)."""
    from gonio.capture.reduction_config import identity_digest

    return identity_digest(camera_identity(identity))


# -- file ----------------------------------------------------------------------------------
_Finite = Annotated[float, Field(allow_inf_nan=False)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class _CameraId(_Strict):
    backend: str
    model: str
    serial: str | None = None
    resolution: tuple[int, int] | None = None


class _Rejected(_Strict):
    label: str
    reason: str


class CalibrationRecord(_Strict):
    """``[camera.calibration]``: how the camera table was made."""

    created: str
    digest: Annotated[str, Field(pattern=r"^sha256:[0-9a-f]{64}$")]
    camera: _CameraId
    K_std: tuple[_Finite, _Finite, _Finite, _Finite]
    dist_std: tuple[_Finite, _Finite, _Finite, _Finite, _Finite]
    rms_px: Annotated[float, Field(ge=0, allow_inf_nan=False)]
    n_points: Annotated[int, Field(ge=0)]
    views_used: list[str]
    view_errors_px: dict[str, _Finite] = Field(default_factory=dict)
    views_rejected: list[_Rejected] = Field(default_factory=list)
    #: (9, 9) covariance of fx fy cx cy k1 k2 p1 p2 k3 (files written before it: None).
    covariance: tuple[tuple[_Finite, ...], ...] | None = None

    @field_validator("covariance")
    @classmethod
    def _nine_by_nine(cls, v: Any) -> Any:
        if v is not None and (len(v) != 9 or any(len(row) != 9 for row in v)):
            raise ValueError("expected a 9 x 9 matrix (fx fy cx cy k1 k2 p1 p2 k3)")
        return v


_Row = tuple[_Finite, _Finite, _Finite]


class CameraFile(_Strict):
    """``[camera]`` of a camera calibration file (the reduction's fields + the record)."""

    K: tuple[_Row, _Row, _Row]
    dist: tuple[_Finite, _Finite, _Finite, _Finite, _Finite]
    width: Annotated[int, Field(ge=1)]
    height: Annotated[int, Field(ge=1)]
    cfa_pattern: str | None = None
    calibration: CalibrationRecord


def calibration_document(
    calibration: CameraCalibration,
    camera_identity_: Mapping[str, Any],
    *,
    cfa_pattern: str | None = None,
    created: str | None = None,
) -> dict[str, Any]:
    """The TOML document :func:`write_camera_calibration` writes (a dict)."""
    ident = camera_identity(camera_identity_, calibration.image_size)
    w, h = calibration.image_size
    cam: dict[str, Any] = {
        "K": [[float(x) for x in row] for row in calibration.K],
        "dist": [float(x) for x in calibration.dist],
        "width": int(w),
        "height": int(h),
    }
    if cfa_pattern:
        cam["cfa_pattern"] = cfa_pattern
    ident_doc = {k: v for k, v in ident.items() if v is not None}
    cam["calibration"] = {
        "created": created or datetime.now(UTC).isoformat(timespec="seconds"),
        "digest": camera_digest(ident),
        "camera": ident_doc,
        "K_std": [float(x) for x in calibration.K_std],
        "dist_std": [float(x) for x in calibration.dist_std],
        "rms_px": float(calibration.rms_px),
        "n_points": int(calibration.n_points),
        "views_used": list(calibration.used),
        "view_errors_px": {k: float(v) for k, v in calibration.view_errors.items()},
        "views_rejected": [{"label": r.label, "reason": r.reason} for r in calibration.rejected],
    }
    if calibration.covariance is not None:
        cam["calibration"]["covariance"] = [
            [float(x) for x in row] for row in np.asarray(calibration.covariance, float)
        ]
    return {"camera": cam}


def write_camera_calibration(
    path: str | os.PathLike,
    calibration: CameraCalibration,
    camera_identity: Mapping[str, Any],
    *,
    cfa_pattern: str | None = None,
    force: bool = False,
) -> Path:
    """Write ``camera.toml``: a ``[camera]`` table the reduction takes (K, dist, width,
    height, cfa_pattern) and ``[camera.calibration]`` (standard deviations, RMS, views
    used and rejected, the camera's identity and its digest).

    Raises
    ------
    CameraCalibrationError
        ``path`` exists and ``force`` is not given (nothing is written).
    """
    import tomli_w

    from gonio.atomic import write_text_atomic

    path = Path(path)
    if path.exists() and not force:
        raise CameraCalibrationError(
            f"{path} exists; pass --force (force=True) to replace it, or choose another file"
        )
    doc = calibration_document(calibration, camera_identity, cfa_pattern=cfa_pattern)
    write_text_atomic(path, tomli_w.dumps(doc))
    return path


def load_camera_calibration(path: str | os.PathLike) -> CameraFile:
    """Read and validate a camera calibration file.

    Raises
    ------
    ConfigError
        Unreadable TOML, or a field missing or out of its model (file and field named).
    FileFormatError
        The digest does not match the camera identity recorded beside it.
    """
    from gonio.config import read_toml, validate

    data = read_toml(path, "camera calibration")
    if "camera" not in data:
        raise FileFormatError(path, "no [camera] table", "camera")
    cam = validate(CameraFile, data["camera"], f"{path} [camera]")
    if camera_digest(cam.calibration.camera.model_dump()) != cam.calibration.digest:
        raise FileFormatError(
            path,
            "the digest does not match the camera identity recorded beside it (edited by hand?)",
            "camera.calibration.digest",
        )
    return cam


def check_camera(calibration: CameraFile | Mapping[str, Any], identity: Any) -> None:
    """Refuse a calibration made for another camera.

    Parameters
    ----------
    calibration
        A loaded :class:`CameraFile`, or a mapping with a ``digest`` (or the document's
        ``camera.calibration``).
    identity
        The camera in use (see :func:`camera_identity`).

    Raises
    ------
    CameraMismatch
        Naming both digests and both cameras.
    """
    if isinstance(calibration, CameraFile):
        rec: Mapping[str, Any] = calibration.calibration.model_dump()
    else:
        rec = calibration.get("camera", {}).get("calibration", calibration)
    want = camera_digest(identity)
    have = rec.get("digest")
    if have != want:
        raise CameraMismatch(
            f"the camera calibration is for camera {rec.get('camera')} (digest {have}), "
            f"the camera in use is {camera_identity(identity)} (digest {want}); calibrate "
            "this camera with 'gonio calibrate camera'"
        )
