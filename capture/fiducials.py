"""Where is the camera, and which pixels see which part of the sample?

The sample holder carries a ChArUco board (OpenCV ``cv2.aruco.CharucoBoard``) centred on
the sample-frame origin, columns along +x, rows along -y (see
:class:`gonio.simulator.scene.Board`).  From one frame this module

1. builds a grey image from the raw mosaic (each CFA channel scaled to a common level,
   which is exact for the neutral black and white print),
2. detects the board with OpenCV 5's ``CharucoDetector.detectBoard``,
3. solves the camera pose with ``cv2.solvePnP(..., SOLVEPNP_IPPE)`` (the points are
   planar) refined by Levenberg-Marquardt,
4. maps the sample's region of interest: every pixel whose ray meets the sample plane
   inside the ROI, split into a grid of regions, with its sample-frame point, ``wo`` and
   (given the light position) ``wi``.  With lens distortion (OpenCV coefficients) a
   pixel's ray is its undistorted one (:func:`undistorted_coordinates`), as the board's
   pose is solved with the distortion.

Pixel coordinates follow OpenCV: the centre of pixel (row r, column c) is at u = c, v = r.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from gonio.capture.raw import RawFrame
from gonio.errors import ReductionError
from gonio.radiometry.frames import angle_between as angle_between  # gonio.capture.reduce
from gonio.radiometry.frames import rotation_angle


@lru_cache(maxsize=8)
def _cv_board(nx: int, ny: int, square: float, marker: float, dictionary: str) -> Any:
    # built once per board: a session detects it in every pose
    if not hasattr(cv2.aruco, dictionary):
        raise ReductionError(f"unknown cv2.aruco dictionary {dictionary!r}")
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    return cv2.aruco.CharucoBoard((nx, ny), square, marker, d)


@dataclass(frozen=True)
class BoardSpec:
    """The holder's ChArUco board and where it sits in the sample frame.

    Parameters
    ----------
    squares_x, squares_y
        Number of chessboard squares along the board's columns and rows.
    square_length, marker_length
        Square and marker side, metres.
    dictionary
        Name of a ``cv2.aruco`` predefined dictionary, e.g. ``"DICT_4X4_50"``.
    board_to_sample
        ``(R, t)`` with ``p_sample = R @ p_board + t``; by default the board is centred on
        the origin with its columns along +x and its rows along -y.
    """

    squares_x: int = 7
    squares_y: int = 7
    square_length: float = 0.02
    marker_length: float = 0.015
    dictionary: str = "DICT_4X4_50"
    board_to_sample: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None

    @classmethod
    def from_mapping(cls, m: Mapping[str, Any]) -> BoardSpec:
        """From a mapping with the fields of the simulator's ``[holder.board]`` table.

        Raises
        ------
        ValueError
            A field of the wrong type or out of range (named), before OpenCV sees it.
        """
        import cv2

        keys = ("squares_x", "squares_y", "square_length", "marker_length", "dictionary")
        fields = {k: m[k] for k in keys if k in m}
        for k in ("squares_x", "squares_y"):
            v = fields.get(k, 7)
            if isinstance(v, bool) or not isinstance(v, int) or v < 2:
                raise ValueError(f"{k} = {v!r}: expected a whole number of squares >= 2")
        for k in ("square_length", "marker_length"):
            v = fields.get(k, 0.02 if k == "square_length" else 0.015)
            if isinstance(v, bool) or not isinstance(v, int | float) or not 0 < v < 10:
                raise ValueError(f"{k} = {v!r}: expected a positive length in metres")
        if fields.get("marker_length", 0.015) >= fields.get("square_length", 0.02):
            raise ValueError("marker_length must be smaller than square_length")
        d = fields.get("dictionary", "DICT_4X4_50")
        if not isinstance(d, str) or not d.startswith("DICT_") or not hasattr(cv2.aruco, d):
            raise ValueError(f"dictionary = {d!r}: expected a cv2.aruco dictionary name")
        from gonio.charuco import board_markers_problem

        # OpenCV builds a board with more markers than the dictionary has IDs and then
        # finds none of it: refused here, as the scene and `calibrate` refuse it
        problem = board_markers_problem(
            fields.get("squares_x", 7), fields.get("squares_y", 7), d
        )
        if problem is not None:
            raise ValueError(problem)
        return cls(**fields)

    def cv_board(self) -> Any:
        """The OpenCV board (object points in metres, board frame)."""
        return _cv_board(
            self.squares_x, self.squares_y, self.square_length, self.marker_length, self.dictionary
        )

    def transform(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(R, t)`` taking board-frame points to the sample frame."""
        if self.board_to_sample is not None:
            R, t = self.board_to_sample
            return np.asarray(R, float), np.asarray(t, float)
        w, h = self.squares_x * self.square_length, self.squares_y * self.square_length
        return np.diag([1.0, -1.0, -1.0]), np.array([-w / 2, h / 2, 0.0])


@dataclass(frozen=True)
class CameraPose:
    """Camera pose in the sample frame from the fiducials.

    Attributes
    ----------
    rotation
        (3, 3) sample-to-camera rotation (OpenCV axes: x right, y down, z forward).
    translation
        (3,) sample origin in camera coordinates, metres.
    position
        (3,) camera centre in the sample frame, metres.
    reprojection_rms
        RMS reprojection error of the board corners, pixels.
    n_corners
        Number of ChArUco corners used.
    covariance
        (6, 6) covariance of ``(rvec, tvec)``: the Rodrigues vector of ``rotation`` (rad)
        and ``translation`` (m), from the corners' reprojection residuals
        (:func:`pose_covariance`); None when the pose did not come from corners.
    intrinsics_sensitivity
        (6, 9) first-order change of ``(rvec, tvec)`` per unit change of the camera
        intrinsics ``(fx, fy, cx, cy, k1, k2, p1, p2, k3)`` the pose was solved with
        (:func:`pose_intrinsics_sensitivity`): how an error of the camera calibration
        moves the board pose; None when the pose did not come from corners.
    """

    rotation: NDArray[np.float64]
    translation: NDArray[np.float64]
    position: NDArray[np.float64]
    reprojection_rms: float
    n_corners: int
    covariance: NDArray[np.float64] | None = None
    intrinsics_sensitivity: NDArray[np.float64] | None = None

    def angle_to(self, rotation: ArrayLike) -> float:
        """Angle (rad) of the rotation between this pose and another world-to-camera one."""
        return float(rotation_angle(self.rotation @ np.asarray(rotation, float).T))


def _cell_scales(frame: RawFrame) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(2, 2) black level and (2, 2) level of each CFA position (median of a subsample).

    Dividing by the level equalises the channels on the neutral black and white print, so
    the Bayer pattern does not show as a checker texture.
    """
    black = frame.cell_black if frame.raw is not None else frame.black_level[:2, :2]
    src = frame.raw if frame.raw is not None else frame.linear + frame.black_level
    # ~2500 samples per CFA position: the median is then good to ~2 %, plenty to
    # equalise the channels for corner refinement
    step = 2 * max(1, int(np.sqrt(src.size / 1e4)) // 2 * 2 + 1)
    h, w = (src.shape[0] // 2) * 2, (src.shape[1] // 2) * 2
    sub = [
        [src[i:h:step, j:w:step].astype(np.float64) - black[i, j] for j in range(2)]
        for i in range(2)
    ]
    # The medians are taken over the same 2x2 cells, the ones with signal: a plain
    # median over the whole frame falls on the cliff between the unlit background (~0)
    # and the board when each covers about half of the frame, and then came out ~0 for
    # one channel and ~100 DN for another (a Bayer checker over the whole grey image:
    # no marker was found in a plainly visible board).  On the neutral print the cells'
    # channel values are one level times the cell's brightness, so the medians over any
    # set of cells keep the channels' ratios.
    total = sub[0][0] + sub[0][1] + sub[1][0] + sub[1][1]
    lit = total > 0.2 * float(np.percentile(total, 99))
    level = np.empty((2, 2))
    for i in range(2):
        for j in range(2):
            vals = sub[i][j][lit] if np.count_nonzero(lit) >= 16 else sub[i][j].ravel()
            med = float(np.median(vals))
            level[i, j] = med if med > 0 else max(float(sub[i][j].max()), 1.0)
    return np.asarray(black, float), level


def grey_image(frame: RawFrame, factor: int = 1) -> NDArray[np.float32]:
    """Channel-equalised grey image of the mosaic, binned by ``factor`` (1 or even).

    Saturated pixels keep their clipped value, which reads as white.
    """
    src = frame.raw if frame.raw is not None else frame.linear + frame.black_level
    H, W = frame.shape
    if factor == 1:
        black, level = _cell_scales(frame)
        out = src.astype(np.float32)
        for i in range(2):
            for j in range(2):
                out[i::2, j::2] = (out[i::2, j::2] - black[i, j]) / level[i, j]
        return out
    if factor % 2:
        raise ValueError(f"binning factor must be 1 or even, got {factor}")
    # Every factor x factor block holds each CFA position equally often, so a plain block
    # mean is already a neutral grey (the channels need no equalising at this scale).
    img = src
    if img.dtype not in (np.uint16, np.float32):
        img = img.astype(np.float32)
    low = _halvings(img, factor)  # as binned_grey_uint8 bins: equal to it by contract
    black = frame.cell_black if frame.raw is not None else frame.black_level[:2, :2]
    return low.astype(np.float32) - np.float32(np.mean(black))


def to_uint8(img: NDArray[np.float32], name: str = "frame") -> NDArray[np.uint8]:
    """8-bit grey for marker detection: ``255 sqrt(img / top)``, ``top`` the 99.5th
    percentile (brighter pixels clip).

    The square root (a gamma of 1/2, which also evens out shot noise) keeps a dim board
    next to a bright sample legible: under grazing light a glossy sample's highlight sets
    the percentile, and a linear scale left the board a dozen grey levels, too few for
    the markers' bits (a 60 deg pose lost 18 of its 24 corners that way).
    """
    top = float(np.percentile(img[::4, ::4], 99.5))
    if not np.isfinite(top) or top <= 0:
        raise ReductionError(f"{name}: frame has no usable signal to find the board in")
    x = np.clip(img * np.float32(1.0 / top), 0.0, 1.0)
    return (np.sqrt(x) * 255.0 + 0.5).astype(np.uint8)


def grey_from_mosaic(frame: RawFrame) -> NDArray[np.uint8]:
    """An 8-bit full-resolution grey image of the mosaic for marker detection."""
    return to_uint8(grey_image(frame, 1), frame.name)


def binned_grey_uint8(frame: RawFrame, factor: int) -> NDArray[np.uint8]:
    """``to_uint8(grey_image(frame, factor))``, faster for a camera mosaic.

    The block mean (``INTER_AREA``) of the raw uint16 mosaic, minus the black level,
    through to_uint8's tone curve.
    """
    if frame.raw is None or factor == 1:
        return to_uint8(grey_image(frame, factor), frame.name)
    if factor % 2:
        raise ValueError(f"binning factor must be 1 or even, got {factor}")
    low = _halvings(frame.raw, factor)
    black = np.float32(np.mean(frame.cell_black))
    top = float(np.percentile(low[::4, ::4], 99.5)) - float(black)
    if not np.isfinite(top) or top <= 0:
        raise ReductionError(f"{frame.name}: frame has no usable signal to find the board in")
    # to_uint8's tone curve as a lookup table over the binned values (uint16): the same
    # numbers for a fraction of the per-pixel arithmetic
    codes = np.arange(int(low.max()) + 1, dtype=np.float32) - black
    x = np.clip(codes * np.float32(1.0 / top), 0.0, 1.0)
    lut = (np.sqrt(x) * 255.0 + 0.5).astype(np.uint8)
    # np.take, not lut[low]: the same gather without fancy indexing's general machinery,
    # half the time (0.4 against 0.9 ms for an 800 x 600 image)
    return np.take(lut, low)


def _halvings(raw: NDArray, factor: int) -> NDArray:
    """Block means of ``raw`` over ``factor x factor`` blocks: for a power of 2 as
    successive halvings (an integer image's each rounded to the nearest integer), else
    in one step.

    OpenCV's ``INTER_AREA`` halves a uint16 image in a vectorised path, 0.17 ms for a
    1600 x 1200 mosaic, while a factor of 4 in one step takes its generic path, 0.58 ms;
    two halvings take 0.22 ms.  Each halving rounds, so a value may differ from the one
    step mean by 1 DN.  Marker finding only needs the corners' whereabouts (each is then
    refined on the mosaic): such a change moves where the refinement starts, and where
    it ends by less than ``cornerSubPix``'s 1e-3 px stopping step (3e-4 px at most on
    the reduction benchmark's 1600 x 1200 session, against 0.06-0.07 px reprojection RMS).

    Parameters
    ----------
    raw
        (H, W) mosaic (uint16) or grey image (float32).
    factor
        Block side, pixels (1 or even: a whole number of Bayer cells).

    Returns
    -------
    ndarray
        (H // factor, W // factor), ``raw``'s dtype.
    """
    H, W = raw.shape
    h, w = H // factor * factor, W // factor * factor
    low = raw[:h, :w]
    if factor & (factor - 1):
        return cv2.resize(low, (w // factor, h // factor), interpolation=cv2.INTER_AREA)
    f = 1
    while f < factor:
        f *= 2
        low = cv2.resize(low, (w // f, h // f), interpolation=cv2.INTER_AREA)
    return low


def _marker_corners(board: BoardSpec) -> NDArray[np.float64]:
    """(n, 4, 3) corners of the board's markers in the sample frame, metres."""
    R, t = board.transform()
    return np.asarray(board.cv_board().getObjPoints(), float) @ R.T + t


def binning_for(
    board: BoardSpec,
    K: ArrayLike,
    expected: CameraPose,
    shape: tuple[int, int],
    *,
    min_factor: int = 1,
    min_marker_px: float = 20.0,
) -> int:
    """Coarsest binning (a power of 2, at least ``min_factor``) that keeps every marker,
    as the expected camera pose shows it, at least ``min_marker_px`` pixels on a side.

    Marker detection costs grow with the pixel count while the markers are often far
    larger than their 6x6 cells need (3 pixels a cell decode reliably).
    """
    K = np.asarray(K, float)
    pc = _marker_corners(board) @ expected.rotation.T + expected.translation
    if not np.all(pc[..., 2] > 0):
        return min_factor
    uv = (pc @ K.T)[..., :2] / pc[..., 2:3]
    side = float(np.linalg.norm(np.roll(uv, -1, axis=1) - uv, axis=-1).min())
    factor = min_factor
    while side / (2 * factor) >= min_marker_px and shape[1] / (2 * factor) >= 160:
        factor *= 2
    return factor


def detect_pose_in_frame(
    frame: RawFrame,
    board: BoardSpec,
    K: ArrayLike,
    dist: ArrayLike | None = None,
    *,
    max_width: int = 800,
    min_corners: int = 6,
    expected: CameraPose | None = None,
) -> CameraPose:
    """Find the board in a raw frame and solve the camera pose, fast on large sensors.

    Markers are detected on an image binned down to at most ``max_width`` pixels (marker
    detection costs grow with the pixel count, and markers are large), or coarser when
    the ``expected`` pose (the rig's report) shows the markers big enough for it
    (:func:`binning_for`; if the board is not found there, at ``max_width`` again); each
    ChArUco corner found is then refined with ``cv2.cornerSubPix`` on the
    full-resolution mosaic around it, so the pose keeps full-resolution accuracy.
    """
    H, W = frame.shape
    factor = 1
    while W / factor > max_width:
        factor *= 2
    if factor == 1 and expected is None:
        return detect_pose(
            grey_from_mosaic(frame), board, K, dist, name=frame.name, min_corners=min_corners
        )
    coarse = factor
    if expected is not None:
        coarse = binning_for(board, K, expected, (H, W), min_factor=factor)
    try:
        corners, ids = _detect_corners(
            binned_grey_uint8(frame, coarse), board, frame.name, min_corners
        )
        factor = coarse
    except ReductionError:
        if coarse == factor:
            raise
        corners, ids = _detect_corners(
            binned_grey_uint8(frame, factor), board, frame.name, min_corners
        )
    if factor == 1:
        try:
            return _solve(board, corners, ids, K, dist)
        except ReductionError as exc:
            raise ReductionError(f"{frame.name}: {exc}") from None
    full = corners * factor + (factor - 1) / 2.0
    spacing = _corner_spacing(full, ids, board)
    half_win = int(np.clip(round(0.12 * spacing), 3, 15))
    black, level = _cell_scales(frame)
    src = frame.raw if frame.raw is not None else frame.linear + frame.black_level
    refined = full.copy()
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 1e-3)
    pad = half_win + 3
    size = 2 * pad + 1
    # Black level and channel level of every pixel of a crop, for the four CFA phases a
    # crop can start on (a crop starting on phase (a, b) reads the tiled cell from (a, b),
    # index 2 a + b): equalising a crop is then one subtraction and one division.
    big = [np.tile(np.asarray(x, np.float32), (pad + 2, pad + 2)) for x in (black, level)]
    blk_tiles, lev_tiles = (
        np.stack([t[a : a + size, b : b + size] for a in range(2) for b in range(2)]) for t in big
    )
    # Every corner's crop at once (one gather, one conversion and one equalisation for
    # all of them: the per-corner numpy calls cost more than cornerSubPix itself); the
    # same float32 operations element by element, so the same crops.
    c0 = np.array([int(round(u)) for u in full[:, 0]], np.int64) - pad
    r0 = np.array([int(round(v)) for v in full[:, 1]], np.int64) - pad
    inside = np.flatnonzero((c0 >= 0) & (r0 >= 0) & (c0 + size <= W) & (r0 + size <= H))
    if len(inside):
        step = np.arange(size)
        rows = (r0[inside, None] + step)[:, :, None]
        cols = (c0[inside, None] + step)[:, None, :]
        phase = 2 * (r0[inside] % 2) + c0[inside] % 2
        crops = (src[rows, cols].astype(np.float32) - blk_tiles[phase]) / lev_tiles[phase]
        for crop, n in zip(crops, inside, strict=True):
            # Python ints, as the offsets were: a float32 point plus numpy int64s would
            # be promoted to float64 before the sum, and round differently
            cn, rn = int(c0[n]), int(r0[n])
            u, v = full[n]
            pt = np.array([[[u - cn, v - rn]]], np.float32)
            cv2.cornerSubPix(crop, pt, (half_win, half_win), (-1, -1), crit)
            refined[n] = pt[0, 0] + (cn, rn)
    return _solve(board, refined, ids, K, dist)


def _corner_spacing(corners: NDArray, ids: NDArray, board: BoardSpec) -> float:
    """Median image distance between neighbouring ChArUco corners, pixels."""
    d = np.linalg.norm(corners[:, None, :] - corners[None, :, :], axis=-1)
    d[d == 0] = np.inf
    return float(np.median(d.min(axis=1)))


def _detect_corners(
    image: NDArray[np.uint8], board: BoardSpec, name: str, min_corners: int
) -> tuple[NDArray[np.float64], NDArray[np.int32]]:
    # First one adaptive-threshold window (half the cost), then OpenCV's default three
    # if that misses the board (uneven light, small markers).
    fast = cv2.aruco.DetectorParameters()
    fast.adaptiveThreshWinSizeMin = fast.adaptiveThreshWinSizeMax = 11
    for params in (fast, cv2.aruco.DetectorParameters()):
        det = cv2.aruco.CharucoDetector(board.cv_board(), cv2.aruco.CharucoParameters(), params)
        corners, ids, _mc, mids = det.detectBoard(image)
        n = 0 if ids is None else len(ids)
        if n >= min_corners:
            break
    if n < min_corners:
        nm = 0 if mids is None else len(mids)
        raise ReductionError(
            f"{name}: ChArUco board not visible ({n} corners, {nm} markers found; "
            f"need {min_corners} corners)"
        )
    return corners.reshape(-1, 2).astype(np.float64), ids.reshape(-1).astype(np.int32)


def _solve(
    board: BoardSpec, corners: NDArray, ids: NDArray, K: ArrayLike, dist: ArrayLike | None
) -> CameraPose:
    K = np.asarray(K, dtype=np.float64)
    dist = np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64)
    cvb = board.cv_board()
    obj, img = cvb.matchImagePoints(
        corners.reshape(-1, 1, 2).astype(np.float32), ids.reshape(-1, 1)
    )
    obj = obj.reshape(-1, 3).astype(np.float64)
    img = img.reshape(-1, 2).astype(np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
    if ok:
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec)
    # a degenerate corner set (a few corners on one line) can give NaN rather than fail
    if not ok or not (np.isfinite(rvec).all() and np.isfinite(tvec).all()):
        raise ReductionError(
            f"solvePnP found no pose for the board from {len(ids)} corners (degenerate set)"
        )
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))
    R_bc = cv2.Rodrigues(rvec)[0]
    R_bs, t_bs = board.transform()
    # p_cam = R_bc p_board + t_bc and p_board = R_bs^T (p_sample - t_bs)
    R = R_bc @ R_bs.T
    t = tvec.ravel() - R @ t_bs
    obj_s = obj @ R_bs.T + t_bs
    cov, sens = _pose_statistics(obj_s, img, R, t, K, dist)
    return CameraPose(R, t, -R.T @ t, rms, len(ids), cov, sens)


def _pose_jacobian(
    obj: NDArray[np.float64], rotation: ArrayLike, translation: ArrayLike, K: ArrayLike, dist
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Projections (n, 2) and ``cv2.projectPoints``' Jacobian (2n, 6 + 4 + 5): rvec, tvec,
    fx, fy, cx, cy, then k1, k2, p1, p2, k3."""
    rvec = cv2.Rodrigues(np.asarray(rotation, np.float64))[0]
    tvec = np.asarray(translation, np.float64).reshape(3, 1)
    d = np.zeros(5)
    if dist is not None:
        dd = np.asarray(dist, np.float64).ravel()
        if len(dd) > 5:
            d = dd
        else:
            d[: len(dd)] = dd
    proj, jac = cv2.projectPoints(obj, rvec, tvec, np.asarray(K, np.float64), d)
    return proj.reshape(-1, 2), jac[:, :15]


def pose_intrinsics_sensitivity(
    points: ArrayLike,
    rotation: ArrayLike,
    translation: ArrayLike,
    K: ArrayLike,
    dist: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """How the least-squares pose follows an error of the intrinsics it was solved with.

    At the solution the residuals' gradient vanishes; to first order a change ``dk`` of
    the intrinsics moves the pose by ``-(J_p^T J_p)^-1 J_p^T J_k dk``, ``J_p`` and
    ``J_k`` the projections' Jacobians (``cv2.projectPoints``) with respect to the pose
    and to the intrinsics.

    Parameters
    ----------
    points
        (n, 3) object points (the frame the pose maps from), m.
    rotation, translation
        The solved pose (object -> camera).
    K, dist
        The intrinsics it was solved with (px; OpenCV distortion, None: none).

    Returns
    -------
    ndarray
        (6, 9) ``d(rvec, tvec) / d(fx, fy, cx, cy, k1, k2, p1, p2, k3)`` (rad or m per
        px or per unit coefficient); NaN for a degenerate point set.
    """
    return _pose_statistics(points, None, rotation, translation, K, dist)[1]


def pose_covariance(
    points: ArrayLike,
    image_points: ArrayLike,
    rotation: ArrayLike,
    translation: ArrayLike,
    K: ArrayLike,
    dist: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """Covariance of a camera pose solved from point correspondences.

    ``sigma^2 (J^T J)^-1``, with ``J`` the (2n, 6) Jacobian of the projections
    (``cv2.projectPoints``) with respect to ``(rvec, tvec)`` and ``sigma^2`` the residuals'
    sum of squares over their ``2n - 6`` degrees of freedom: the first-order covariance of
    the least-squares pose when every coordinate has the same independent noise.

    Parameters
    ----------
    points
        (n, 3) object points in the frame the pose maps from (here: the sample frame), m.
    image_points
        (n, 2) detected image points, px.
    rotation, translation
        The solved pose: (3, 3) rotation and (3,) translation (object -> camera), m.
    K, dist
        Camera matrix (px) and OpenCV distortion coefficients (None: none).

    Returns
    -------
    ndarray
        (6, 6) covariance of ``(rvec, tvec)`` in rad^2, rad m, m^2 (NaN when the points
        cannot determine the pose: fewer than 4, or a degenerate set).
    """
    return _pose_statistics(points, image_points, rotation, translation, K, dist)[0]


def _pose_statistics(
    points: ArrayLike,
    image_points: ArrayLike | None,
    rotation: ArrayLike,
    translation: ArrayLike,
    K: ArrayLike,
    dist: ArrayLike | None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`pose_covariance` and :func:`pose_intrinsics_sensitivity` from one
    Jacobian and one normal matrix (both need the same ones: computing them once saves
    a projection and a condition number's SVD for every board pose).

    Parameters
    ----------
    points, rotation, translation, K, dist
        As for :func:`pose_covariance`.
    image_points
        (n, 2) detected image points, px; None: the covariance is not wanted (NaN).

    Returns
    -------
    tuple of ndarray
        (6, 6) covariance and (6, 9) sensitivity, each NaN where the other function
        gives NaN.
    """
    obj = np.asarray(points, np.float64).reshape(-1, 3)
    n = len(obj)
    bad = (np.full((6, 6), np.nan), np.full((6, 9), np.nan))
    if n < 4:
        return bad
    proj, jac = _pose_jacobian(obj, rotation, translation, K, dist)
    J, Jk = jac[:, :6], jac[:, 6:15]
    JtJ = J.T @ J
    if not np.all(np.isfinite(JtJ)) or np.linalg.cond(JtJ) > 1e15:
        return bad
    sens = -np.linalg.solve(JtJ, J.T @ Jk)
    if image_points is None:
        return bad[0], sens
    res = proj - np.asarray(image_points, np.float64).reshape(-1, 2)
    sigma2 = float(np.sum(res**2)) / (2 * n - 6)
    cov = sigma2 * np.linalg.inv(JtJ)
    return 0.5 * (cov + cov.T), sens


def detect_pose(
    image: NDArray[np.uint8],
    board: BoardSpec,
    K: ArrayLike,
    dist: ArrayLike | None = None,
    *,
    name: str = "frame",
    min_corners: int = 6,
) -> CameraPose:
    """Detect the ChArUco board in a grey image and solve the camera pose (sample frame).

    Parameters
    ----------
    image
        8-bit grey image, (H, W).
    board
        The holder's board.
    K
        3x3 camera matrix (pixels, OpenCV convention).
    dist
        Distortion coefficients (OpenCV order), none by default.
    name
        Frame name for messages.
    min_corners
        Fewest ChArUco corners accepted.

    Raises
    ------
    ReductionError
        When the board is not visible (fewer than ``min_corners`` corners found).
    """
    corners, ids = _detect_corners(image, board, name, min_corners)
    try:
        return _solve(board, corners, ids, K, dist)
    except ReductionError as exc:
        raise ReductionError(f"{name}: {exc}") from None


@dataclass(frozen=True)
class RoiGeometry:
    """Where the sample's region of interest falls in one camera pose.

    Attributes
    ----------
    box
        ``(row_slice, col_slice)``: the image crop holding the ROI.
    half_size
        Half width and half height of the ROI on the sample, metres.
    cell
        Width and height of one grid cell, metres.
    limit
        Half width and half height, metres, of the part of the ROI whose pixels are used:
        the ROI less what lies within ``margin_px`` image pixels of the sample's edge
        (:func:`edge_margins`); all of it unless the view is near grazing.
    inner_margin
        Margin kept inside every cell along x and along y, metres
        (:func:`spread_margins`: it bounds the spread of directions within a region).
    grid
        Regions along x (and along y unless ``grid_y`` says otherwise).
    centers
        (grid * grid_y, 2) cell centres on the sample, metres (x, y), in region order
        ``iy * grid + ix`` (``iy`` counted from -y).
    grid_y
        Regions along y; None: ``grid`` (square).
    """

    box: tuple[slice, slice]
    half_size: tuple[float, float]
    cell: tuple[float, float]
    limit: tuple[float, float]
    grid: int
    centers: NDArray[np.float64]
    inner_margin: tuple[float, float] = (0.0, 0.0)
    grid_y: int | None = None

    @property
    def grid_xy(self) -> tuple[int, int]:
        """Regions along x and along y."""
        return (self.grid, self.grid if self.grid_y is None else self.grid_y)


def roi_geometry(
    pose: CameraPose,
    K: ArrayLike,
    shape: tuple[int, int],
    sample_size: tuple[float, float],
    *,
    roi_fraction: float = 0.6,
    grid: int | tuple[int, int] = 3,
    margin_px: float = 2.0,
    dist: ArrayLike | None = None,
    inner_margin: tuple[float, float] = (0.0, 0.0),
) -> RoiGeometry:
    """The ROI's crop and grid in one camera pose (see :func:`map_regions`; ``grid`` an
    int for a square grid or ``(nx, ny)`` regions along x and y).

    With a distorting lens (``dist``, OpenCV coefficients) the crop is the bounding box
    of the ROI's distorted image: its outline (corners and edges, which distortion bends)
    projected with ``cv2.projectPoints``.

    Raises
    ------
    ReductionError
        When the ROI is not in the image or not facing the camera.
    """
    K = np.asarray(K, float)
    hw, hh = 0.5 * roi_fraction * sample_size[0], 0.5 * roi_fraction * sample_size[1]
    corners = np.array([[-hw, -hh, 0], [hw, -hh, 0], [hw, hh, 0], [-hw, hh, 0]])
    pc = corners @ pose.rotation.T + pose.translation
    if not (np.all(pc[:, 2] > 0) and pose.position[2] > 0):
        raise ReductionError("the sample's ROI is behind the camera or seen from below")
    if has_distortion(dist):
        uv = _project_outline(corners, pose, K, dist)
    else:
        uv = (pc @ K.T)[:, :2] / pc[:, 2:3]
    c0, r0 = np.floor(uv.min(0)).astype(int)
    c1, r1 = np.ceil(uv.max(0)).astype(int) + 1
    H, W = shape
    if c0 < 0 or r0 < 0 or c1 > W or r1 > H:
        raise ReductionError(
            f"the sample's ROI (columns {c0}..{c1}, rows {r0}..{r1}) is not inside the "
            f"{W}x{H} image"
        )
    mx, my = edge_margins(pose, K, sample_size, (hw, hh), margin_px)
    limit = (min(hw, 0.5 * sample_size[0] - mx), min(hh, 0.5 * sample_size[1] - my))
    gx, gy = grid_counts(grid)
    cell_x, cell_y = 2 * hw / gx, 2 * hh / gy
    cx, cy = np.meshgrid(-hw + (np.arange(gx) + 0.5) * cell_x, -hh + (np.arange(gy) + 0.5) * cell_y)
    return RoiGeometry(
        (slice(r0, r1), slice(c0, c1)),
        (hw, hh),
        (cell_x, cell_y),
        limit,
        gx,
        np.stack([cx.ravel(), cy.ravel()], axis=1),
        (float(inner_margin[0]), float(inner_margin[1])),
        None if gy == gx else gy,
    )


def grid_counts(grid: int | tuple[int, int]) -> tuple[int, int]:
    """``(nx, ny)`` regions of a grid given as one count per side or as a pair."""
    if isinstance(grid, int | np.integer):
        return int(grid), int(grid)
    gx, gy = grid
    return int(gx), int(gy)


def edge_margins(
    pose: CameraPose,
    K: ArrayLike,
    sample_size: tuple[float, float],
    half_size: tuple[float, float],
    margin_px: float,
) -> tuple[float, float]:
    """How far (metres, along x and along y on the sample) ``margin_px`` image pixels
    reach across the sample's edges next to the ROI.

    A pixel whose centre is ``d`` metres (along x) from the edge ``x = const`` is
    ``d / |grad x|`` pixels from that edge's image, ``grad x`` the gradient of the
    sample-plane ``x`` over the image ``(u, v)`` (a row of the inverse Jacobian of the
    plane's projection): the margin along x is ``margin_px |grad x|``, evaluated where
    the edges meet the ROI's extent and the largest taken.  Along the view's tilt a
    pixel covers ``1 / cos(theta_o)`` times more of the sample than across it, which a
    single margin for both axes (the former rule) cannot say: it blanked every region of
    a 6 x 6 grid at theta_o 60 deg at 320 x 240.

    Parameters
    ----------
    pose
        Camera pose (sample frame).
    K
        Camera matrix, pixels.
    sample_size
        Sample width (x) and height (y), metres, centred on the origin.
    half_size
        The ROI's half width and half height, metres.
    margin_px
        The margin, image pixels.

    Returns
    -------
    (mx, my)
        Metres; inf when an edge point is behind the camera.
    """
    K = np.asarray(K, float)
    sx, sy = 0.5 * sample_size[0], 0.5 * sample_size[1]
    hw, hh = half_size
    R, t = np.asarray(pose.rotation, float), np.asarray(pose.translation, float)
    out = []
    for pts, axis in (
        (np.array([[a * sx, b * hh] for a in (-1, 1) for b in (-1, 0, 1)]), 0),
        (np.array([[a * hw, b * sy] for a in (-1, 0, 1) for b in (-1, 1)]), 1),
    ):
        pc = pts @ R[:, :2].T + t  # (n, 3) camera coordinates of plane points
        z = pc[:, 2]
        if not np.all(z > 0):
            out.append(math.inf)
            continue
        # d(u, v)/d(x, y) of u = fx X/Z + cx, v = fy Y/Z + cy, (X, Y, Z) = R[:, :2] p + t
        J = np.empty((len(pts), 2, 2))
        for r, f in ((0, K[0, 0]), (1, K[1, 1])):
            for c in range(2):
                J[:, r, c] = f * (R[r, c] * z - pc[:, r] * R[2, c]) / z**2
        det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
        # |row `axis` of J^-1| = |d(axis)/d(u, v)|, metres per pixel: J^-1 is
        # [[J11, -J01], [-J10, J00]] / det
        col = 1 - axis
        with np.errstate(divide="ignore", invalid="ignore"):
            grad = np.hypot(J[:, 0, col], J[:, 1, col]) / np.abs(det)
        m = float(np.max(grad)) if np.all(np.isfinite(grad)) else math.inf
        out.append(margin_px * m)
    return out[0], out[1]


def spread_margins(
    positions: list[ArrayLike],
    cell: tuple[float, float],
    half_size: tuple[float, float],
    max_spread_deg: float,
) -> tuple[float, float]:
    """Margins inside each grid cell (metres, along x and along y) that keep the spread
    of directions within a region below ``max_spread_deg`` as seen from every position
    (the camera's and the light's centres).

    A region reports the mean of its pixels' directions while its value is the mean of
    the BRDF over them: on a lobe that flattens the peak by about (spread / lobe
    width)^2, a bias shared by every region at that place of the lobe.  Moving a point
    on the sample by ``dx`` along axis ``a`` turns the unit direction from it towards a
    position P by ``sqrt(1 - (w . e_a)^2) dx / |P - x|``, so along an axis the sample is
    seen foreshortened from P (at grazing views, along the tilt) a whole cell stays
    within the spread and nothing is trimmed, where a fixed margin in pixels or metres
    (the former rule) left oblique regions without pixels.  The rate is taken at the
    ROI's corners and centre (its largest), the margin is what the cell has beyond the
    allowed extent, split between its two sides.

    Parameters
    ----------
    positions
        (3,) points in the sample frame, metres (camera centre, light centre).
    cell
        Cell width and height, metres.
    half_size
        The ROI's half width and half height, metres.
    max_spread_deg
        Largest extent of a region's directions, degrees (full width).

    Returns
    -------
    (mx, my)
        Metres, each in ``[0, cell / 2)``.
    """
    hw, hh = half_size
    q = np.array([[0.0, 0.0, 0.0], *[[a * hw, b * hh, 0.0] for a in (-1, 1) for b in (-1, 1)]])
    rate = np.zeros(2)
    for pos in positions:
        v = np.asarray(pos, float)[None, :] - q
        d = np.linalg.norm(v, axis=1)
        u = v / d[:, None]
        for a in range(2):
            rate[a] = max(rate[a], float(np.max(np.sqrt(1.0 - u[:, a] ** 2) / d)))
    spread = math.radians(max_spread_deg)
    out = []
    for a in range(2):
        allowed = spread / rate[a] if rate[a] > 0 else math.inf
        out.append(max(0.0, 0.5 * (cell[a] - allowed)))
    return out[0], out[1]


#: Round trip (undistort, then distort with ``cv2.projectPoints``) that
#: :func:`undistorted_coordinates` guarantees, pixels.
UNDISTORT_TOLERANCE_PX = 1e-6


def has_distortion(dist: ArrayLike | None) -> bool:
    """Whether OpenCV distortion coefficients bend any ray (None or all zeros do not)."""
    return dist is not None and bool(np.any(np.asarray(dist, dtype=np.float64) != 0.0))


def _project_outline(
    corners: NDArray[np.float64], pose: CameraPose, K: NDArray[np.float64], dist: ArrayLike
) -> NDArray[np.float64]:
    """(n, 2) distorted image (pixels) of a planar polygon's outline, 64 points an edge."""
    t = np.linspace(0.0, 1.0, 64, endpoint=False)[:, None]
    nxt = np.roll(corners, -1, axis=0)
    outline = np.concatenate([a + t * (b - a) for a, b in zip(corners, nxt, strict=True)])
    rvec = cv2.Rodrigues(np.asarray(pose.rotation, float))[0]
    uv, _ = cv2.projectPoints(
        outline, rvec, np.asarray(pose.translation, float), K, np.asarray(dist, float)
    )
    return uv.reshape(-1, 2)


def undistorted_coordinates(
    K: ArrayLike, dist: ArrayLike, box: tuple[slice, slice]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Normalised undistorted coordinates of every pixel centre of a crop.

    Parameters
    ----------
    K
        3x3 camera matrix, pixels (OpenCV convention: pixel centres at integers).
    dist
        OpenCV distortion coefficients (k1, k2, p1, p2[, k3[, ...]]), dimensionless.
    box
        ``(row_slice, col_slice)`` of the crop in the image.

    Returns
    -------
    (x, y)
        Two (h, w) arrays: the pinhole coordinates ``(X / Z, Y / Z)`` of the ray each
        pixel sees (dimensionless), i.e. the points that ``cv2.projectPoints`` distorts
        onto the pixel centres.

    Raises
    ------
    ReductionError
        When neither the Newton iteration nor OpenCV's inverts the distortion to
        :data:`UNDISTORT_TOLERANCE_PX` on the crop's border or its 8-pixel grid
        (coefficients so strong that the lens model folds over inside the image).
    """
    K = np.asarray(K, dtype=np.float64)
    dist = np.asarray(dist, dtype=np.float64)
    v, u = np.mgrid[box[0].start : box[0].stop, box[1].start : box[1].stop]
    h, w = v.shape
    pix = np.stack([u.ravel(), v.ravel()], axis=-1).astype(np.float64).reshape(-1, 1, 2)
    xy = _newton_undistort(K, dist, box, (h, w))
    if xy is None or _round_trip_error(xy, pix, K, dist, h, w)[0] is not None:
        # 20 fixed-point steps take a moderate lens (|k1| ~ 0.2) to ~1e-13 px; the 30
        # allowed are a margin, and the round trip below checks the result
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-15)
        xy = cv2.undistortPoints(pix, K, dist, R=np.eye(3), P=np.eye(3), criteria=crit)
        xy = xy.reshape(-1, 2)
    k, e = _round_trip_error(xy, pix, K, dist, h, w)
    if k is not None:
        raise ReductionError(
            f"camera dist {dist.tolist()}: the distortion cannot be inverted at pixel "
            f"(u={int(pix[k, 0, 0])}, v={int(pix[k, 0, 1])}) (round trip {e:.3g} px, "
            f"expected <= {UNDISTORT_TOLERANCE_PX:g} px); check the camera calibration"
        )
    return xy[:, 0].reshape(h, w).copy(), xy[:, 1].reshape(h, w).copy()


def _newton_undistort(
    K: NDArray[np.float64], dist: NDArray[np.float64], box: tuple[slice, slice], shape: tuple
) -> NDArray[np.float64] | None:
    """(h w, 2) undistorted coordinates by the compiled Newton iteration (five or fewer
    coefficients; ~20x faster than ``cv2.undistortPoints``), or None without numba or for
    OpenCV's longer models."""
    if len(dist) > 5 and np.any(dist[5:] != 0):
        return None
    try:
        from gonio.capture.pose_kernel import undistort_pixels
    except ImportError:
        return None
    d5 = np.zeros(5)
    d5[: min(len(dist), 5)] = dist[:5]
    x, y = np.empty(shape), np.empty(shape)
    cam = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    undistort_pixels(int(box[0].start), int(box[1].start), cam, d5, x, y)
    return np.stack([x.ravel(), y.ravel()], axis=-1)


def _round_trip_error(
    xy: NDArray[np.float64],
    pix: NDArray[np.float64],
    K: NDArray[np.float64],
    dist: NDArray[np.float64],
    h: int,
    w: int,
) -> tuple[int | None, float]:
    """``(index, px)`` of the worst round trip above the tolerance, or ``(None, px)``."""
    # The round trip on the crop's border (farthest from the centre: where the iteration
    # converges slowest) and every 8th row and column: the map is smooth, and
    # cv2.projectPoints over every pixel would cost 4x the undistortion itself.
    sel = np.zeros((h, w), bool)
    sel[::8, ::8] = sel[[0, -1], :] = sel[:, [0, -1]] = True
    idx = np.flatnonzero(sel)
    back, _ = cv2.projectPoints(
        np.concatenate([xy[idx], np.ones((len(idx), 1))], axis=1),
        np.zeros(3),
        np.zeros(3),
        K,
        dist,
    )
    err = np.linalg.norm(back.reshape(-1, 2) - pix.reshape(-1, 2)[idx], axis=1)
    err = np.where(np.isfinite(err), err, np.inf)
    bad = int(np.argmax(err))
    if err[bad] <= UNDISTORT_TOLERANCE_PX:
        return None, float(err[bad])
    return int(idx[bad]), float(err[bad])


def pixel_rays(
    pose: CameraPose,
    K: ArrayLike,
    box: tuple[slice, slice],
    dist: ArrayLike | None = None,
) -> tuple[tuple[NDArray, NDArray, NDArray], NDArray[np.float64]]:
    """Sample-plane point seen by every pixel of a crop, and its natural vignetting.

    Returns ``((x, y, z), vignetting)``: (h, w) arrays; the points are in the sample
    frame, metres (NaN off the plane), the vignetting is cos^4 of the angle to the optical
    axis.  One (h, w) array per component: numpy's batched (h, w, 3) @ (3, 3) products and
    norms over a last axis of 3 are several times slower.

    With a distorting lens (``dist``) each pixel's ray is the undistorted one
    (:func:`undistorted_coordinates`), while the vignetting stays that of the pixel's
    place on the sensor: the cos^4 law is the image side's (the exit pupil seen from the
    pixel), which distortion, a remapping of object-side directions, does not change
    (the simulator's sensor applies it so too).  Without distortion (None or zeros) the
    pinhole expressions run unchanged, to the bit.
    """
    K = np.asarray(K, float)
    x = ((np.arange(box[1].start, box[1].stop, dtype=np.float64) - K[0, 2]) / K[0, 0])[None, :]
    y = ((np.arange(box[0].start, box[0].stop, dtype=np.float64) - K[1, 2]) / K[1, 1])[:, None]
    r2 = x * x + y * y + 1.0
    vign = 1.0 / (r2 * r2)
    if has_distortion(dist):
        assert dist is not None
        x, y = undistorted_coordinates(K, dist, box)
    Rm = pose.rotation
    d = [Rm[0, k] * x + Rm[1, k] * y + Rm[2, k] for k in range(3)]  # sample frame (R^T d)
    C = pose.position
    s = -C[2] / d[2]
    return (C[0] + s * d[0], C[1] + s * d[1], C[2] + s * d[2]), vign


@dataclass(frozen=True)
class RegionMap:
    """The sample's region of interest in one camera pose.

    Attributes
    ----------
    box
        ``(row_slice, col_slice)``: the image crop holding the ROI.
    label
        (h, w) int region index of each pixel in the crop, -1 outside the ROI.
    n_regions
        Number of regions (grid cells).
    centers
        (n_regions, 2) cell centres on the sample, metres (x, y).
    pose
        The camera pose the regions were mapped with.
    K
        The camera matrix.
    dist
        The lens distortion (OpenCV coefficients), None for none.
    """

    box: tuple[slice, slice]
    label: NDArray[np.int64]
    n_regions: int
    centers: NDArray[np.float64]
    pose: CameraPose
    K: NDArray[np.float64]
    extra: dict[str, Any] = field(default_factory=dict)
    dist: NDArray[np.float64] | None = None

    def _rays(self) -> tuple[tuple[NDArray, NDArray, NDArray], NDArray[np.float64]]:
        if "_rays" not in self.extra:  # computed once, on first use
            self.extra["_rays"] = pixel_rays(self.pose, self.K, self.box, self.dist)
        return self.extra["_rays"]

    @property
    def xyz(self) -> tuple[NDArray, NDArray, NDArray]:
        """Three (h, w) arrays: the sample-frame point each pixel sees (NaN off the plane)."""
        return self._rays()[0]

    @property
    def vignetting(self) -> NDArray[np.float64]:
        """(h, w) cos^4 of each pixel's angle to the optical axis (natural vignetting)."""
        return self._rays()[1]

    @property
    def camera_position(self) -> NDArray[np.float64]:
        """(3,) camera centre in the sample frame, metres."""
        return self.pose.position

    @property
    def points(self) -> NDArray[np.float64]:
        """(h, w, 3) sample-frame point seen by each pixel of the crop."""
        return np.stack(self.xyz, axis=-1)

    @property
    def wo(self) -> NDArray[np.float64]:
        """(h, w, 3) unit direction from each pixel's point to the camera centre."""
        return directions_to(self.points, self.camera_position)


def map_regions(
    pose: CameraPose,
    K: ArrayLike,
    shape: tuple[int, int],
    sample_size: tuple[float, float],
    *,
    roi_fraction: float = 0.6,
    grid: int | tuple[int, int] = 3,
    margin_px: float = 2.0,
    dist: ArrayLike | None = None,
    inner_margin: tuple[float, float] = (0.0, 0.0),
) -> RegionMap:
    """Split the sample's central area into ``grid x grid`` regions and find their pixels.

    Parameters
    ----------
    pose
        Camera pose from :func:`detect_pose`.
    K
        Camera matrix (OpenCV convention).
    shape
        Image (mosaic) size (height, width).
    sample_size
        Sample width (x) and height (y), metres; the sample is centred on the origin.
    roi_fraction
        Fraction of each side used (keeps away from the sample's edges).
    grid
        Regions per side; small regions keep the spread of directions in each small.  A
        pair ``(nx, ny)``: regions along x and along y.  Region ``iy * nx + ix``, ``iy``
        counted from -y.
    margin_px
        Pixels whose centre lies closer than this (in the image) to the sample's edge are
        left out, so that no pixel mixes the holder in (:func:`edge_margins`; with the
        ROI inside the sample this removes pixels only near grazing).  It is not a
        margin between regions: a pixel there measures the mean radiance of its
        footprint at its centre's directions in whichever region it is counted, and at
        oblique views a region is only a few pixels across its tilt (at theta_o 80 deg
        a 5 mm region is 1.3 pixels high at 320 x 240), so that a pixel margin there
        left regions without any pixel; ``inner_margin`` trims regions for another
        reason (their spread of directions).
    dist
        Lens distortion (OpenCV coefficients): every pixel's ray is then the undistorted
        one (:func:`pixel_rays`); None or zeros keep the pinhole camera.
    inner_margin
        Metres kept free inside each cell along x and along y (:func:`spread_margins`,
        which bounds the spread of a region's directions): pixels closer to a cell's
        boundary are left out.

    Raises
    ------
    ReductionError
        When the ROI is not in the image or not facing the camera.
    """
    K = np.asarray(K, float)
    roi = roi_geometry(
        pose,
        K,
        shape,
        sample_size,
        roi_fraction=roi_fraction,
        grid=grid,
        margin_px=margin_px,
        dist=dist,
        inner_margin=inner_margin,
    )
    dist = np.asarray(dist, float) if has_distortion(dist) else None
    xyz, vign = rays = pixel_rays(pose, K, roi.box, dist)
    (hw, hh), (cell_x, cell_y), (lx, ly) = roi.half_size, roi.cell, roi.limit
    mx, my = roi.inner_margin
    ux, uy = xyz[0] + hw, xyz[1] + hh
    ix = np.floor(ux / cell_x)
    iy = np.floor(uy / cell_y)
    fx = ux - ix * cell_x
    fy = uy - iy * cell_y
    gx, gy = roi.grid_xy
    inside = (ix >= 0) & (ix < gx) & (iy >= 0) & (iy < gy)
    inside &= (np.abs(xyz[0]) < lx) & (np.abs(xyz[1]) < ly)
    inside &= (fx >= mx) & (fx <= cell_x - mx) & (fy >= my) & (fy <= cell_y - my)
    label = np.where(inside, iy * gx + ix, -1).astype(np.int64)
    return RegionMap(roi.box, label, gx * gy, roi.centers, pose, K, {"_rays": rays}, dist)


def directions_to(points: NDArray[np.float64], position: ArrayLike) -> NDArray[np.float64]:
    """Unit directions from sample points (..., 3) towards a position (3,), e.g. the light."""
    v = np.asarray(position, float) - points
    return v / np.linalg.norm(v, axis=-1, keepdims=True)
