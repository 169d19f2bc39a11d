"""Corner-level views of the as-built world, for statistical tests of the calibrations.

No rendering: the ChArUco corners (and the mirror spot) a camera would see at a pose of
the as-built rig, projected with the world's TRUE intrinsics and Brown-Conrady
distortion, plus Gaussian noise.  A view costs about a millisecond, so a test can
check over many seeds that a calibration's reported uncertainties are honest.

Pixel coordinates are in the OpenCV convention (pixel centres at integer coordinates).
Every function returns plain dicts (``label``, ``joints`` (reported, rad), ``approach``,
...) that the calibrations' observation types are made from.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gonio.simulator.world import JOINTS, World
from gonio.simulator.world_kinematics import (
    NominalRig,
    TruePoses,
    readings_from_pulses,
    true_poses,
)

__all__ = [
    "board_corners",
    "board_views",
    "camera_views",
    "project",
    "simulated_pose",
    "spot_views",
]

Array = NDArray[np.float64]


def project(points_cam: Array, K: Array, dist: Sequence[float]) -> Array:
    """Project camera-frame points through a Brown-Conrady lens (OpenCV's model).

    Parameters
    ----------
    points_cam
        (n, 3) points in the camera frame (OpenCV axes), m; ``z > 0``.
    K
        3x3 camera matrix, px (OpenCV convention).
    dist
        ``(k1, k2, p1, p2, k3)``.

    Returns
    -------
    ndarray (n, 2)
        Pixel coordinates, px.
    """
    P = np.asarray(points_cam, dtype=np.float64)
    k1, k2, p1, p2, k3 = (float(d) for d in dist)
    x, y = P[:, 0] / P[:, 2], P[:, 1] / P[:, 2]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]], axis=1)


def board_corners(board: Any) -> tuple[Array, Array]:
    """ChArUco inner corners of a scene board: (board frame (n, 3), sample frame (n, 3)), m.

    Board frame: OpenCV's ``CharucoBoard.getChessboardCorners()`` (corner ``i`` has
    ChArUco id ``i``); sample frame through ``board.board_to_sample()``.
    """
    obj = np.asarray(board.cv_board().getChessboardCorners(), dtype=np.float64).reshape(-1, 3)
    R, t = board.board_to_sample()
    return obj, obj @ np.asarray(R, float).T + np.asarray(t, float)


def simulated_pose(
    world: World,
    rig_doc: Any,
    joints: Mapping[str, float],
    approach: Mapping[str, int],
    rng: np.random.Generator | None = None,
    label: str = "",
) -> dict[str, Any]:
    """A calibration pose as the rig would reach and report it, without a bus.

    The servos are sent to the nominal pulses of ``joints`` (rad), land within the
    world's ``landing_pulses`` (drawn from ``rng``), and have last moved in the joint
    sense ``approach`` (+1 / -1 per joint).

    Returns
    -------
    dict
        ``label``, ``joints`` (the readings the controller reports, rad, through the
        nominal zero), ``approach``, ``servo_states`` (id -> (pulses, direction)).
    """
    rig = NominalRig.of(rig_doc)
    n = world.servos.landing_pulses
    states = {}
    for s in rig.servos:
        zero = s.zero_deg * 4096.0 / 360.0
        goal = round(
            zero + s.direction * s.gear_ratio * float(joints[s.joint]) * 4096 / (2 * math.pi)
        )
        e = int(rng.integers(-n, n + 1)) if (n and rng is not None) else 0
        states[s.id] = (goal + e, int(approach.get(s.joint, 0)) * s.direction)
    reported = readings_from_pulses(rig, {i: st[0] for i, st in states.items()})
    return {
        "label": label,
        "joints": reported,
        "approach": {j: int(approach.get(j, 0)) for j in JOINTS},
        "servo_states": states,
    }


def _visible(
    cam_pts: Array,
    pix: Array,
    sample_pts: Array,
    poses: TruePoses,
    size: tuple[int, int],
    max_view_deg: float,
) -> Array:
    w, h = size
    to_cam = poses.camera_position - sample_pts
    cos_view = to_cam[:, 2] / np.linalg.norm(to_cam, axis=1)  # the board's normal is +z
    return (
        (cam_pts[:, 2] > 0)
        & (pix[:, 0] >= -0.5)
        & (pix[:, 0] <= w - 0.5)
        & (pix[:, 1] >= -0.5)
        & (pix[:, 1] <= h - 0.5)
        & (cos_view > math.cos(math.radians(max_view_deg)))
    )


def _to_camera(poses: TruePoses, sample_pts: Array) -> Array:
    R = np.asarray(poses.camera_rotation)  # camera -> sample
    return (sample_pts - poses.camera_position) @ R


def board_views(
    world: World,
    rig_doc: Any,
    scene_camera: Any,
    board: Any,
    poses: Iterable[Mapping[str, Any]],
    sigma_px: float,
    rng: np.random.Generator,
    *,
    hidden: tuple[float, float] | None = None,
    max_view_deg: float = 75.0,
    min_corners: int = 6,
) -> list[dict[str, Any]]:
    """The ChArUco corners the as-built camera sees at each pose.

    Parameters
    ----------
    world, rig_doc
        The as-built world and the nominal rig TOML dict.
    scene_camera
        The scene's nominal camera (resolution; the world gives the true intrinsics).
    board
        The scene's :class:`~gonio.simulator.scene.Board`.
    poses
        Dicts with ``joints`` (reported, rad), ``approach`` and ``servo_states`` (see
        :func:`simulated_pose`), optionally ``label``.
    sigma_px
        Standard deviation of the Gaussian noise of each corner coordinate, px.
    rng
        The noise's generator.
    hidden
        (width, height) of a rectangle centred on the sample origin whose corners are
        covered (the sample on its holder), m; None: none covered.
    max_view_deg
        Corners seen more obliquely than this are not detected, deg.
    min_corners
        Views with fewer visible corners are left out.

    Returns
    -------
    list of dict
        ``label``, ``joints``, ``approach``, ``ids`` (ChArUco corner ids),
        ``object_points`` (sample frame, m), ``image_points`` (px).
    """
    K, dist = world.intrinsics(scene_camera)
    rig_doc = NominalRig.of(rig_doc)  # parsed once, not per pose
    _, sample_pts = board_corners(board)
    ids = np.arange(len(sample_pts))
    keep = np.ones(len(sample_pts), bool)
    if hidden is not None:
        keep = ~(
            (np.abs(sample_pts[:, 0]) < hidden[0] / 2) & (np.abs(sample_pts[:, 1]) < hidden[1] / 2)
        )
    out = []
    for k, pose in enumerate(poses):
        truth = true_poses(world, rig_doc, pose["servo_states"])
        cam = _to_camera(truth, sample_pts)
        with np.errstate(divide="ignore", invalid="ignore"):
            pix = project(cam, K, dist)
        vis = keep & _visible(cam, pix, sample_pts, truth, scene_camera.resolution, max_view_deg)
        if vis.sum() < min_corners:
            continue
        noisy = pix[vis] + rng.normal(0.0, sigma_px, (int(vis.sum()), 2))
        out.append(
            {
                "label": pose.get("label") or f"pose {k}",
                "joints": dict(pose["joints"]),
                "approach": dict(pose["approach"]),
                "ids": ids[vis],
                "object_points": sample_pts[vis],
                "image_points": noisy,
            }
        )
    return out


def spot_views(
    world: World,
    rig_doc: Any,
    scene_camera: Any,
    mirror_size: tuple[float, float],
    poses: Iterable[Mapping[str, Any]],
    sigma_px: float,
    rng: np.random.Generator,
) -> list[dict[str, Any]]:
    """The light's centre seen in a flat mirror lying in the sample plane.

    The spot is the projection of the MIRRORED light centre ``(Lx, Ly, -Lz)`` (sample
    frame); a pose gives a spot only where the reflection point (where the line from the
    camera to the mirrored light crosses z = 0) lies on the mirror (``mirror_size`` =
    (width, height), m, centred on the origin) and projects inside the image.

    Returns
    -------
    list of dict
        ``label``, ``joints``, ``approach``, ``image_point`` (2,), px, with noise.
    """
    K, dist = world.intrinsics(scene_camera)
    rig_doc = NominalRig.of(rig_doc)  # parsed once, not per pose
    w, h = scene_camera.resolution
    out = []
    for k, pose in enumerate(poses):
        truth = true_poses(world, rig_doc, pose["servo_states"])
        L = np.asarray(truth.light_position, float) * np.array([1.0, 1.0, -1.0])
        C = np.asarray(truth.camera_position, float)
        if C[2] <= 0 or L[2] >= 0:
            continue
        s = C[2] / (C[2] - L[2])
        hit = C + s * (L - C)
        if abs(hit[0]) > mirror_size[0] / 2 or abs(hit[1]) > mirror_size[1] / 2:
            continue
        cam = _to_camera(truth, L[None, :])
        if cam[0, 2] <= 0:
            continue
        pix = project(cam, K, dist)[0]
        if not (-0.5 <= pix[0] <= w - 0.5 and -0.5 <= pix[1] <= h - 0.5):
            continue
        out.append(
            {
                "label": pose.get("label") or f"pose {k}",
                "joints": dict(pose["joints"]),
                "approach": dict(pose["approach"]),
                "image_point": pix + rng.normal(0.0, sigma_px, 2),
            }
        )
    return out


def camera_views(
    world: World,
    rig_doc: Any,
    scene_camera: Any,
    board: Any,
    poses: Iterable[Mapping[str, Any]],
    sigma_px: float,
    rng: np.random.Generator,
    *,
    max_view_deg: float = 75.0,
    min_corners: int = 6,
) -> list[dict[str, Any]]:
    """Views for a camera calibration: the board corners in the board frame (as
    ``cv2.calibrateCamera`` takes them), in the camera frame (truth), and their noisy
    pixels.

    Returns
    -------
    list of dict
        ``label``, ``ids``, ``object_points`` (board frame, z = 0, m),
        ``camera_points`` (camera frame, m), ``image_points`` (px), and the true board
        pose ``R`` (3x3), ``t`` (3,) with ``camera_points = object_points @ R.T + t``.
    """
    K, dist = world.intrinsics(scene_camera)
    rig_doc = NominalRig.of(rig_doc)  # parsed once, not per pose
    board_pts, sample_pts = board_corners(board)
    Rb, tb = board.board_to_sample()
    ids = np.arange(len(board_pts))
    out = []
    for k, pose in enumerate(poses):
        truth = true_poses(world, rig_doc, pose["servo_states"])
        cam = _to_camera(truth, sample_pts)
        with np.errstate(divide="ignore", invalid="ignore"):
            pix = project(cam, K, dist)
        vis = _visible(cam, pix, sample_pts, truth, scene_camera.resolution, max_view_deg)
        if vis.sum() < min_corners:
            continue
        Rcs = np.asarray(truth.camera_rotation).T  # sample -> camera
        R = Rcs @ np.asarray(Rb, float)
        t = Rcs @ (np.asarray(tb, float) - truth.camera_position)
        out.append(
            {
                "label": pose.get("label") or f"view {k}",
                "ids": ids[vis],
                "object_points": board_pts[vis],
                "camera_points": cam[vis],
                "image_points": pix[vis] + rng.normal(0.0, sigma_px, (int(vis.sum()), 2)),
                "R": R,
                "t": t,
            }
        )
    return out
