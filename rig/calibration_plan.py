"""Calibration plans: the joint poses a camera or rig calibration is shot at.

:func:`camera_calibration_poses` gives varied views of the holder's board for the camera
intrinsics (obliquities up to 50 deg about different axes, through the stage tilt, the
camera azimuth and the spin, which turns the tilt's axis in the board).
:func:`rig_calibration_poses` gives what makes every parameter of
:mod:`gonio.rig.calibration` observable: board views over wide ranges of tilt, spin and
camera azimuth, visited in an order that approaches each joint from both sides, then
mirror views (the camera at the mirror direction of the light) at several light
azimuths, tilts and spins, swept both ways.  Every pose is reachable by the nominal
kinematics (``Kinematics.joints_refusal`` is None) and every move keeps the arms clear
(``Kinematics.path_refusal`` is None).

:func:`write_plan` writes a plan TOML of ``[[joint_poses]]``; :func:`check_observable`
runs the observability analysis on the poses (their predicted corners and spots) before
anything moves.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from gonio.rig.asbuilt import rig_poses
from gonio.rig.calibration import CameraPrior, Observability, observability, project_points
from gonio.rig.calibration_data import BoardObservation, SpotObservation
from gonio.rig.calibration_record import CalibrationError
from gonio.rig.config import JOINT_NAMES, RigConfig
from gonio.rig.kinematics import Kinematics

__all__ = [
    "JointPose",
    "approaches",
    "camera_calibration_poses",
    "check_observable",
    "default_board_points",
    "default_camera",
    "predicted_observations",
    "rig_calibration_poses",
    "write_plan",
]

Array = NDArray[np.float64]
_FIELDS = ("light_azimuth_deg", "camera_azimuth_deg", "stage_tilt_deg", "stage_spin_deg")

#: Radius around the sample centre within which a mirror spot must fall, m (a mirror of
#: the sample's size, 50 mm, with a margin for the as-built errors).
MIRROR_RADIUS_M = 0.02
#: Steepest board view a plan asks for (angle between the board normal and the camera), deg.
MAX_OBLIQUITY_DEG = 55.0


@dataclass(frozen=True)
class JointPose:
    """One pose of a calibration plan (degrees, the plan file's ``[[joint_poses]]``)."""

    light_azimuth_deg: float
    camera_azimuth_deg: float
    stage_tilt_deg: float
    stage_spin_deg: float
    target: Literal["sample", "mirror"] = "sample"
    label: str = ""

    def joints_rad(self) -> dict[str, float]:
        """Joint name -> angle, rad."""
        return {
            j: math.radians(getattr(self, f)) for j, f in zip(JOINT_NAMES, _FIELDS, strict=True)
        }

    def to_dict(self) -> dict[str, float | str]:
        """The ``[[joint_poses]]`` entry."""
        d: dict[str, float | str] = {f: round(float(getattr(self, f)), 6) for f in _FIELDS}
        d["target"] = self.target
        if self.label:
            d["label"] = self.label
        return d


def default_board_points(
    squares_x: int = 7, squares_y: int = 7, square_length: float = 0.02
) -> Array:
    """The inner chessboard corners of a ChArUco board centred on the sample, sample
    frame (m), shape ((squares_x - 1) (squares_y - 1), 3)."""
    xs = (np.arange(1, squares_x) - squares_x / 2) * square_length
    ys = (np.arange(1, squares_y) - squares_y / 2) * square_length
    gx, gy = np.meshgrid(xs, ys)
    return np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)


def default_camera(
    width: int = 640, height: int = 480, fov_deg: float = 26.0, std_px: float = 1.0
) -> CameraPrior:
    """A distortion-free camera guess for planning (horizontal field of view ``fov_deg``)."""
    f = width / 2 / math.tan(math.radians(fov_deg) / 2)
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    return CameraPrior(
        K=K,
        dist=np.zeros(5),
        K_std=np.full(4, std_px),
        dist_std=np.array([1e-3, 1e-3, 1e-4, 1e-4, 0.0]),
        rms_px=0.3,
        width=width,
        height=height,
    )


def approaches(
    poses: Sequence[JointPose], start: Mapping[str, float] | None = None
) -> list[dict[str, int]]:
    """Each pose's approach side per joint (+1 increasing, -1 decreasing, 0 unknown):
    the sign of the move into it, kept from the move before when the joint stays put.

    ``start`` is the pose (rad) the rig comes from (None: unknown, 0 until it moves).
    """
    out = []
    prev = dict(start) if start is not None else None
    side = dict.fromkeys(JOINT_NAMES, 0)
    for p in poses:
        q = p.joints_rad()
        if prev is not None:
            for j in JOINT_NAMES:
                d = q[j] - prev[j]
                if abs(d) > 1e-9:
                    side[j] = 1 if d > 0 else -1
        out.append(dict(side))
        prev = q
    return out


def _reachable(kin: Kinematics, pose: JointPose, prev: JointPose | None) -> bool:
    q = pose.joints_rad()
    if kin.joints_refusal(q) is not None:
        return False
    return prev is None or kin.path_refusal(prev.joints_rad(), q) is None


def _obliquity_deg(tilt: float, cam_az: float) -> float:
    # both arms level: the board normal is (cos t, 0, sin t), the camera (cos a, sin a, 0)
    return math.degrees(math.acos(math.cos(math.radians(tilt)) * math.cos(math.radians(cam_az))))


def _board_pose(
    kin: Kinematics, tilt: float, spin: float, cam: float, label: str
) -> JointPose | None:
    """The board view with a light arm placed to light it, or None when none is reachable."""
    for gap in (25.0, 40.0, 60.0, 15.0):
        p = JointPose(cam - gap, cam, tilt, spin, "sample", label)
        if _reachable(kin, p, None):
            return p
    return None


def _order(
    kin: Kinematics, poses: list[JointPose], rng: np.random.Generator, start: JointPose | None
) -> list[JointPose]:
    """A random visiting order (so each joint is approached from both sides, the sides of
    different joints uncorrelated) whose every move keeps the arms clear."""
    rest = [poses[i] for i in rng.permutation(len(poses))]
    out: list[JointPose] = []
    prev = start
    while rest:
        for i, p in enumerate(rest):
            if _reachable(kin, p, prev):
                out.append(rest.pop(i))
                prev = out[-1]
                break
        else:  # nothing reachable from here: drop the first (never expected on a sane rig)
            rest.pop(0)
    return out


def _home(config: RigConfig) -> JointPose:
    h = config.motion.home_deg
    return JointPose(*(float(h[j]) for j in JOINT_NAMES), "sample", "home")


def _labelled(poses: list[JointPose], what: str) -> list[JointPose]:
    return [dataclasses.replace(p, label=f"{what} {i}") for i, p in enumerate(poses)]


def camera_calibration_poses(config: RigConfig) -> list[JointPose]:
    """Board views for the camera intrinsics: frontal, 20 deg and 45 deg rings of
    obliquity in eight directions (tilt and camera azimuth), each at two spins."""
    kin = Kinematics(config)
    rings = [(0.0, 0.0)]
    for r in (20.0, 45.0):
        for k in range(8):
            a = math.radians(45.0 * k)
            rings.append((r * math.sin(a), r * math.cos(a)))
    out = []
    for n, (tilt, cam) in enumerate(rings):
        for spin in (0.0, 35.0 + 10 * n):
            p = _board_pose(kin, round(tilt, 3), spin, round(cam, 3), "")
            if p is not None:
                out.append(p)
    return _labelled(_order(kin, out, np.random.default_rng(1), _home(config)), "camera view")


def rig_calibration_poses(config: RigConfig, *, seed: int = 0) -> list[JointPose]:
    """Board views, then mirror views, for ``gonio calibrate rig`` (see the module text).

    Board views: tilts -50..50 deg, camera azimuths -40..40 deg (obliquity at most
    :data:`MAX_OBLIQUITY_DEG`), spins over the whole turn, in a seeded random order.
    Mirror views: light azimuths -60..-10 deg with the camera at the mirror azimuth, tilts
    -1, 0, 1 deg and four spins, the light swept up and down.  The tilt stays small
    because each degree moves the light's reflection ~7.7 mm off the mirror's centre:
    with 2 deg, the as-built errors (arm and tilt offsets of up to 2 deg) and the light's
    own image (~4.5 mm wide on the mirror) pushed the spot over the edge of a 50 mm
    mirror, where the edge cuts it and its centroid moves by several pixels.
    """
    kin = Kinematics(config)
    rng = np.random.default_rng(seed)
    boards = []
    for tilt in (-50.0, -35.0, -20.0, -5.0, 10.0, 25.0, 40.0, 50.0):
        for cam in (-40.0, -20.0, 0.0, 20.0, 40.0):
            if _obliquity_deg(tilt, cam) > MAX_OBLIQUITY_DEG:
                continue
            for spin in rng.choice(np.arange(-180.0, 180.0, 30.0), size=2, replace=False):
                p = _board_pose(kin, tilt, float(spin), cam, "")
                if p is not None:
                    boards.append(p)
    boards = _labelled(_order(kin, boards, rng, _home(config)), "board")
    mirrors = []
    lights = [-60.0, -50.0, -40.0, -30.0, -20.0, -10.0]
    sweeps = [(0.0, 0.0), (1.0, 90.0), (-1.0, 180.0), (0.0, -90.0)]
    for k, (tilt, spin) in enumerate(sweeps):
        for a in lights if k % 2 == 0 else lights[::-1]:
            # the camera at the mirror direction of the light (both arms level, tilt ~ 0)
            p = JointPose(a, -a, tilt, spin, "mirror", "")
            prev = mirrors[-1] if mirrors else (boards[-1] if boards else None)
            if _reachable(kin, p, prev):
                mirrors.append(p)
    return boards + _labelled(mirrors, "mirror")


def predicted_observations(
    config: RigConfig,
    poses: Sequence[JointPose],
    camera: CameraPrior,
    *,
    board_points: Array | None = None,
    start: Mapping[str, float] | None = None,
) -> tuple[list[BoardObservation], list[SpotObservation]]:
    """The corners and spots the nominal rig predicts at the poses (noise-free), keeping
    the corners inside the image and the spots that fall on the mirror."""
    pts = default_board_points() if board_points is None else np.asarray(board_points, float)
    w = camera.width or int(round(2 * camera.K[0][2] + 1))
    h = camera.height or int(round(2 * camera.K[1][2] + 1))
    intr = camera.vector()
    sides = approaches(poses, config.home_rad if start is None else start)
    boards, spots = [], []
    for p, side in zip(poses, sides, strict=True):
        q = p.joints_rad()
        poses_ = rig_poses(config, q, side)
        R, C = poses_.camera_rotation, poses_.camera_position
        if p.target == "sample":
            uv = project_points((pts - C) @ R, intr)
            inside = (uv[:, 0] > 2) & (uv[:, 0] < w - 3) & (uv[:, 1] > 2) & (uv[:, 1] < h - 3)
            if inside.sum() >= 6 and C[2] > 0:
                boards.append(BoardObservation(p.label, q, side, pts[inside], uv[inside]))
        else:
            L = poses_.light_position * np.array([1.0, 1.0, -1.0])
            s = C[2] / (C[2] - L[2])  # where the camera's ray to the mirrored light meets z = 0
            hit = C + s * (L - C)
            if np.hypot(hit[0], hit[1]) <= MIRROR_RADIUS_M:
                spots.append(SpotObservation(p.label, q, side, project_points((L - C) @ R, intr)))
    return boards, spots


def check_observable(
    config: RigConfig,
    poses: Sequence[JointPose],
    camera: CameraPrior | None = None,
    *,
    board_points: Array | None = None,
) -> Observability:
    """The observability analysis of a rig calibration plan, before anything moves.

    Raises
    ------
    CalibrationError
        Naming every parameter the plan would leave undetermined and what it lacks.
    """
    camera = camera or default_camera()
    boards, spots = predicted_observations(config, poses, camera, board_points=board_points)
    obs = observability(config, boards, spots, camera)
    obs.raise_if_refused(f"the plan ({len(boards)} board views, {len(spots)} mirror views)")
    return obs


_PLAN_HEADER = """\
# A {kind} calibration plan written by `gonio calibrate plan --kind {kind}`.
# Each [[joint_poses]] entry is one pose (degrees), visited in this order: the order
# approaches every joint from both sides, which the rig calibration needs to measure
# backlash.  target = "sample" shoots the holder's board, "mirror" the mirror in the
# sample's place (a real rig asks the operator to put it there).
# The bracket's two fixed exposures: a short one for the light's image in the mirror,
# a long one for the board.
"""


def write_plan(
    path: str | Path,
    poses: Sequence[JointPose],
    *,
    kind: str = "rig",
    name: str | None = None,
    exposures_s: tuple[float, float] = (0.0001, 0.02),
    settle_s: float = 0.5,
    width: int = 640,
    height: int = 480,
    force: bool = False,
) -> Path:
    """Write a plan TOML of ``[[joint_poses]]`` (the capture session's plan format).

    ``exposures_s``: the short one images the light in the mirror, the long one the
    board.  The light seen in a mirror is the light's own radiance (x 0.9), thousands of
    times the lit board's: with the simulator's default scene 0.0005 s saturated every
    spot, 0.0001 s puts its peak near half of full scale.

    Raises
    ------
    CalibrationError
        When ``poses`` is empty or ``path`` exists and ``force`` is false.
    """
    import tomli_w

    from gonio.atomic import atomic_path

    path = Path(path)
    if not poses:
        raise CalibrationError(f"not writing {path}: the plan has no poses")
    if path.exists() and not force:
        raise CalibrationError(f"{path} exists; not overwritten (use --force to replace it)")
    doc = {
        "name": name or f"{kind} calibration",
        "description": f"{len(poses)} joint poses for `gonio calibrate {kind}`",
        "settle_s": settle_s,
        "bracket": {
            "policy": "fixed",
            "exposures_s": [float(t) for t in exposures_s],
            "iso": 100.0,
            "f_number": 8.0,
        },
        "simulation": {"width": int(width), "height": int(height)},
        "joint_poses": [p.to_dict() for p in poses],
    }
    with atomic_path(path) as tmp:
        tmp.write_text(_PLAN_HEADER.format(kind=kind) + tomli_w.dumps(doc), encoding="utf-8")
    return path
