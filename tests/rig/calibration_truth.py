"""Simulated rig-calibration observations for the tests, made without gonio.rig.calibration.

A random as-built rig is drawn (the canonical parameters of i15 section 1) and written into
a RigConfig with scipy's rotations (not ``apply_parameters``); corners and spots are
projected with ``rig_poses`` of that truth and ``cv2.projectPoints``, plus Gaussian noise.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from gonio.rig.asbuilt import rig_poses
from gonio.rig.calibration_data import BoardObservation, SpotObservation
from gonio.rig.config import JOINT_NAMES

JOINT_FIELDS = ("light_azimuth_deg", "camera_azimuth_deg", "stage_tilt_deg", "stage_spin_deg")
WIDTH, HEIGHT = 640, 480
#: the camera calibration's standard deviations: fx, fy, cx, cy, k1, k2, p1, p2, k3 (fixed)
CAMERA_STD = np.array([1.5, 1.5, 1.0, 1.0, 3e-3, 2e-2, 2e-4, 2e-4, 0.0])


def draw_values(rng: np.random.Generator, nominal) -> dict[str, float]:
    g = nominal.geometry
    v = {}
    for j in JOINT_NAMES:
        v[f"{j}.offset"] = rng.normal(0, 1.5)
    for j in JOINT_NAMES:
        v[f"{j}.backlash"] = rng.uniform(0.1, 0.4)
    v["stage_tilt.compliance_a"] = rng.normal(0, 0.1)
    v["stage_tilt.compliance_b"] = rng.normal(0, 0.1)
    v["light_elevation"] = g.light_elevation_deg + rng.normal(0, 0.5)
    v["camera_elevation"] = g.camera_elevation_deg + rng.normal(0, 0.5)
    v["camera_radius"] = g.camera_radius_m + rng.normal(0, 0.005)
    for a in "xyz":
        v[f"camera_mount_{a}"] = rng.normal(0, 0.5)
    v["tilt_axis_pitch"] = rng.normal(0, 0.5)
    v["spin_axis_yaw"] = rng.normal(0, 0.5)
    for a in "xy":
        v[f"holder_tilt_{a}"] = rng.normal(0, 0.5)
    v["holder_offset_x"] = rng.normal(0, 0.002)
    v["holder_offset_y"] = rng.normal(0, 0.002)
    v["holder_offset_z"] = rng.uniform(0.001, 0.006)
    for a in "xy":
        v[f"stage_offset_{a}"] = rng.normal(0, 0.002)
    return v


def truth_config(nominal, v: dict[str, float]):
    """The as-built RigConfig of the canonical values, from the table's definitions."""
    g = nominal.geometry
    k0 = np.array(g.tilt_axis, float) / np.linalg.norm(g.tilt_axis)
    n0 = np.array(g.rest_normal, float)
    r0 = np.array(g.rest_reference, float)
    w = np.cross(k0, [0, 0, 1.0])
    w /= np.linalg.norm(w)
    u = np.cross(k0, n0)
    u /= np.linalg.norm(u)
    k = Rotation.from_rotvec(w * math.radians(v["tilt_axis_pitch"])).apply(k0)
    Ru = Rotation.from_rotvec(u * math.radians(v["spin_axis_yaw"]))
    servos = []
    for s in nominal.servos:
        upd = {
            "zero_deg": s.zero_deg - s.direction * s.gear_ratio * v[f"{s.joint}.offset"],
            "backlash_deg": v[f"{s.joint}.backlash"],
        }
        if s.joint == "stage_tilt":
            upd["compliance_deg"] = (v["stage_tilt.compliance_a"], v["stage_tilt.compliance_b"])
        servos.append(s.model_copy(update=upd))
    geo = g.model_copy(
        update={
            "light_elevation_deg": v["light_elevation"],
            "camera_elevation_deg": v["camera_elevation"],
            "camera_radius_m": v["camera_radius"],
            "camera_mount_deg": tuple(v[f"camera_mount_{a}"] for a in "xyz"),
            "tilt_axis": tuple(k),
            "rest_normal": tuple(Ru.apply(n0)),
            "rest_reference": tuple(Ru.apply(r0)),
            "holder_tilt_deg": (v["holder_tilt_x"], v["holder_tilt_y"]),
            "holder_offset_m": tuple(v[f"holder_offset_{a}"] for a in "xyz"),
            "stage_offset_m": (v["stage_offset_x"], v["stage_offset_y"], 0.0),
        }
    )
    return nominal.model_copy(update={"servos": tuple(servos), "geometry": geo})


def draw_camera(rng: np.random.Generator):
    """(true intrinsics vector, calibrated K, dist, K_std, dist_std)."""
    f = 320 / math.tan(math.radians(13))
    true = np.array(
        [
            f * (1 + rng.normal(0, 0.01)),
            f * (1 + rng.normal(0, 0.01)),
            319.5 + rng.normal(0, 4),
            239.5 + rng.normal(0, 4),
            rng.normal(-0.1, 0.05),
            rng.normal(0.1, 0.1),
            rng.normal(0, 1e-3),
            rng.normal(0, 1e-3),
            0.0,
        ]
    )
    cal = true + CAMERA_STD * rng.standard_normal(9)
    K = np.array([[cal[0], 0, cal[2]], [0, cal[1], cal[3]], [0, 0, 1.0]])
    return true, K, cal[4:], CAMERA_STD[:4], CAMERA_STD[4:]


def board_points(n: int = 7, square: float = 0.02) -> np.ndarray:
    """Inner corners of an n x n board centred on the sample (sample frame, m)."""
    c = (np.arange(1, n) - n / 2) * square
    gx, gy = np.meshgrid(c, c)
    return np.stack([gx.ravel(), gy.ravel(), 0 * gx.ravel()], 1)


def sides(poses, home_deg):
    """Approach side of each joint at each pose: sign of the move into it (kept when still)."""
    prev = np.array([home_deg[j] for j in JOINT_NAMES])
    s = np.zeros(4)
    out = []
    for p in poses:
        q = np.array([getattr(p, f) for f in JOINT_FIELDS])
        d = np.sign(q - prev)
        s = np.where(d != 0, d, s)
        out.append({j: int(x) for j, x in zip(JOINT_NAMES, s, strict=True)})
        prev = q
    return out


def simulate(
    nominal, v, poses, intr, rng, sigma_board=0.2, sigma_spot=0.15, force_side=None,
    view_shift_px=0.0,
):  # fmt: skip
    """(boards, spots) observed at the plan's poses by the rig of values ``v``;
    ``force_side`` (joint -> +1/-1) pretends every pose approached that joint from one side;
    ``view_shift_px``: each board view's corners also share one random image shift of that
    std per axis (an error of the view, as its detection or its board pose makes)."""
    truth = truth_config(nominal, v)
    K = np.array([[intr[0], 0, intr[2]], [0, intr[1], intr[3]], [0, 0, 1.0]])
    dist = np.asarray(intr[4:], float)
    pts = board_points()
    boards, spots = [], []
    for p, side in zip(poses, sides(poses, nominal.motion.home_deg), strict=True):
        side = {**side, **(force_side or {})}
        reading = {
            j: math.radians(getattr(p, f)) for j, f in zip(JOINT_NAMES, JOINT_FIELDS, strict=True)
        }
        true_reading = {j: reading[j] + math.radians(v[f"{j}.offset"]) for j in JOINT_NAMES}
        pose = rig_poses(truth, true_reading, side)
        R_sc = pose.camera_rotation.T
        rvec, _ = cv2.Rodrigues(R_sc)
        tvec = -R_sc @ pose.camera_position
        if p.target == "sample":
            uv = cv2.projectPoints(pts, rvec, tvec, K, dist)[0].reshape(-1, 2)
            ok = (uv[:, 0] > 3) & (uv[:, 0] < WIDTH - 4) & (uv[:, 1] > 3) & (uv[:, 1] < HEIGHT - 4)
            uv = uv + sigma_board * rng.standard_normal(uv.shape)
            if view_shift_px:
                uv = uv + view_shift_px * rng.standard_normal(2)
            boards.append(BoardObservation(p.label, reading, side, pts[ok], uv[ok]))
        else:
            L = pose.light_position * np.array([1, 1, -1.0])
            uv = cv2.projectPoints(L[None], rvec, tvec, K, dist)[0].reshape(2)
            spots.append(
                SpotObservation(p.label, reading, side, uv + sigma_spot * rng.standard_normal(2))
            )
    return boards, spots
