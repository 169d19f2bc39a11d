"""Rig calibration: the as-built kinematic parameters from board views and mirror spots.

The parameters are the canonical ones of the as-built model (``gonio.rig.asbuilt``),
degrees or metres as their unit says (:data:`PARAMETERS`); ``light_radius`` and the terms
of :data:`NOT_OBSERVABLE` cannot be measured and keep their nominal values.

The solve (:func:`calibrate_rig`) is a weighted least-squares fit
(``scipy.optimize.least_squares``, no robust loss, so its covariance holds) of

- every board view: the projection of its corners (sample frame) through the camera pose
  the model gives at the view's encoder readings and approach sides, minus the detected
  corners;
- every mirror spot: the projection of the mirrored light centre ``(Lx, Ly, -Lz)``
  (sample frame; the mirror lies in the sample plane) minus the spot's centroid;
- the camera intrinsics, parameters too, tied to the camera calibration by prior
  residuals ``(p - p_cal) / std_cal`` so their uncertainty reaches the rig parameters.

Each kind's sigma is its residual RMS corrected for the degrees of freedom it used (the
hat matrix' trace over its rows); the weights are iterated once on that.  A view whose
RMS exceeds :data:`REJECT_FACTOR` times its kind's median is reported, removed and the
fit repeated.  The covariance is ``(J^T W J)^-1`` at the solution, raised where the
views' residuals show errors their corners share (a view-clustered sandwich,
:func:`_view_correlated`).

Observability (:func:`observability`) is judged before the solve from the Jacobian at the
nominal rig, and after it at the estimate: a parameter whose standard deviation would
exceed :data:`OBSERVABLE_FRACTION` of its expected magnitude (:data:`PARAMETERS`) is
refused, named, with what the plan lacks.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gonio.errors import ParameterError
from gonio.radiometry.frames import normalize, rotation_about
from gonio.rig.asbuilt import rig_poses
from gonio.rig.calibration_data import BoardObservation, SpotObservation
from gonio.rig.calibration_record import (
    CalibrationError,
    CalibrationRecord,
    ParameterCovariance,
    ParameterEstimate,
    rig_digest,
)
from gonio.rig.config import JOINT_NAMES, RigConfig, rig_config_from_dict

__all__ = [
    "CameraPrior",
    "INTRINSIC_NAMES",
    "NOT_OBSERVABLE",
    "OBSERVABLE_FRACTION",
    "PARAMETERS",
    "PARAMETER_NAMES",
    "Observability",
    "RigCalibration",
    "ViewResidual",
    "apply_parameters",
    "calibrate_rig",
    "observability",
    "parameters_of",
    "project_points",
    "write_calibrated_rig",
]

Array = NDArray[np.float64]
_Z = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class _Spec:
    unit: str
    #: Expected magnitude of the as-built term on a lab rig (deg or m): scales the
    #: Jacobian and is the yardstick of observability.
    magnitude: float


def _build_parameters() -> dict[str, _Spec]:
    p: dict[str, _Spec] = {}
    for j in JOINT_NAMES:
        p[f"{j}.offset"] = _Spec("deg", 2.0)
    for j in JOINT_NAMES:
        p[f"{j}.backlash"] = _Spec("deg", 0.25)
    p["stage_tilt.compliance_a"] = _Spec("deg", 0.1)
    p["stage_tilt.compliance_b"] = _Spec("deg", 0.1)
    p["light_elevation"] = _Spec("deg", 0.5)
    p["camera_elevation"] = _Spec("deg", 0.5)
    p["camera_radius"] = _Spec("m", 0.005)
    for a in "xyz":
        p[f"camera_mount_{a}"] = _Spec("deg", 0.5)
    p["tilt_axis_pitch"] = _Spec("deg", 0.5)
    p["spin_axis_yaw"] = _Spec("deg", 0.5)
    for a in "xy":
        p[f"holder_tilt_{a}"] = _Spec("deg", 0.5)
    for a in "xyz":
        p[f"holder_offset_{a}"] = _Spec("m", 0.002)
    for a in "xy":
        p[f"stage_offset_{a}"] = _Spec("m", 0.002)
    return p


#: Canonical parameter name -> unit and expected magnitude (i15 section 1; all but
#: ``light_radius``).
PARAMETERS: dict[str, _Spec] = _build_parameters()
PARAMETER_NAMES: tuple[str, ...] = tuple(PARAMETERS)
#: OpenCV intrinsics refined with the rig (px, then Brown-Conrady coefficients).
INTRINSIC_NAMES: tuple[str, ...] = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
_INTRINSIC_UNITS = ("px", "px", "px", "px", "1", "1", "1", "1", "1")

#: A parameter is refused when its standard deviation exceeds this fraction of its
#: expected magnitude: beyond it the estimate says little more than "about the nominal".
OBSERVABLE_FRACTION = 1.0
#: A view whose residual RMS exceeds this many times its kind's median is rejected.
REJECT_FACTOR = 5.0
#: Fewer mirror views than this cannot pin the light's azimuth offset, backlash (both
#: sides) and elevation with margin.
MIN_MIRROR_VIEWS = 6
#: Fewer board views than this cannot separate the camera arm from the stage terms.
MIN_BOARD_VIEWS = 10

_LIGHT_PARAMETERS = ("light_azimuth.offset", "light_azimuth.backlash", "light_elevation")

#: Terms no calibration of this rig can measure, and why (i15 section 1).
NOT_OBSERVABLE: dict[str, str] = {
    "arm azimuth errors": "the same rotation about the same axis as the azimuth servos' zero "
    "offsets (light_azimuth.offset, camera_azimuth.offset)",
    "arm sag": "the arms' elevation never changes, so their load never changes: the sag is a "
    "constant elevation change, inside light_elevation and camera_elevation",
    "azimuth and spin compliance": "their axes are vertical (the spin is balanced about its "
    "axis): the gravity torque does not change with the angle",
    "light_radius": "the mirror spot gives the light's direction from the sample; its "
    "distance changes directions by < 1e-3 deg over the sample, and the irradiance scale "
    "cancels in the reference-target calibration (same distance for both)",
    "tilt axis yaw": "a common offset of both arm zeros plus spin_axis_yaw",
    "tilt axis position along itself": "moves nothing the camera or the light sees",
    "rest orientation about the tilt or spin axis": "the same as the stage_tilt or "
    "stage_spin zero offset",
}


# ------------------------------------------------------------------ parameters <-> config
def _frame_vectors(nominal: RigConfig) -> tuple[Array, Array, Array, Array, Array]:
    g = nominal.geometry
    k0 = normalize(np.asarray(g.tilt_axis, float))
    if abs(k0[2]) > 1e-9:
        raise ParameterError(
            f"the nominal rig's tilt_axis {list(g.tilt_axis)} is not horizontal: calibrate "
            "from the nominal configuration (as drawn), not a calibrated one"
        )
    n0 = normalize(np.asarray(g.rest_normal, float))
    r0 = normalize(np.asarray(g.rest_reference, float))
    w = normalize(np.cross(k0, _Z))  # the tilt axis pitches about this
    u = normalize(np.cross(k0, n0))  # the spin axis yaws about this
    return k0, n0, r0, w, u


def _nominal_values(nominal: RigConfig) -> dict[str, float]:
    return parameters_of(nominal, nominal)


def apply_parameters(
    nominal: RigConfig,
    values: Mapping[str, float],
    *,
    validate: bool = True,
    _frames: tuple[Array, ...] | None = None,
) -> RigConfig:
    """The rig configuration with the as-built parameters ``values`` (canonical names,
    deg or m); names left out keep the nominal's values.

    Parameters
    ----------
    nominal
        The rig as drawn (horizontal ``tilt_axis``).
    values
        Canonical parameter name -> value in its unit (:data:`PARAMETERS`).
    validate
        Validate the result as a rig configuration (the solver's inner loop skips it).

    Raises
    ------
    ParameterError
        An unknown name, or a nominal rig whose tilt axis is not horizontal.
    ConfigError
        A value the configuration refuses (e.g. a negative backlash).
    """
    if _frames is None:
        unknown = sorted(set(values) - set(PARAMETER_NAMES))
        if unknown:
            raise ParameterError(
                f"unknown rig calibration parameter(s) {unknown}; known: {list(PARAMETER_NAMES)}"
            )
    k0, n0, r0, w, u = _frame_vectors(nominal) if _frames is None else _frames
    v = dict(_nominal_values(nominal)) if len(values) < len(PARAMETER_NAMES) else {}
    v.update({k: float(x) for k, x in values.items()})
    servos = []
    for s in nominal.servos:
        upd: dict = {
            "zero_deg": s.zero_deg - s.direction * s.gear_ratio * v[f"{s.joint}.offset"],
            "backlash_deg": v[f"{s.joint}.backlash"],
        }
        if s.joint == "stage_tilt":
            upd["compliance_deg"] = (v["stage_tilt.compliance_a"], v["stage_tilt.compliance_b"])
        servos.append(s.model_copy(update=upd))
    pitch, yaw = math.radians(v["tilt_axis_pitch"]), math.radians(v["spin_axis_yaw"])
    Ry = rotation_about(u, yaw)
    geo = {
        "light_elevation_deg": v["light_elevation"],
        "camera_elevation_deg": v["camera_elevation"],
        "camera_radius_m": v["camera_radius"],
        "camera_mount_deg": tuple(v[f"camera_mount_{a}"] for a in "xyz"),
        "tilt_axis": tuple(float(c) for c in rotation_about(w, pitch) @ k0),
        "rest_normal": tuple(float(c) for c in Ry @ n0),
        "rest_reference": tuple(float(c) for c in Ry @ r0),
        "holder_tilt_deg": tuple(v[f"holder_tilt_{a}"] for a in "xy"),
        "holder_offset_m": tuple(v[f"holder_offset_{a}"] for a in "xyz"),
        "stage_offset_m": (v["stage_offset_x"], v["stage_offset_y"], 0.0),
    }
    config = nominal.model_copy(
        update={"servos": tuple(servos), "geometry": nominal.geometry.model_copy(update=geo)}
    )
    if validate:
        data = config.model_dump(mode="json", exclude_none=True)
        config = rig_config_from_dict(data, "<calibrated rig>")
    return config


def _signed_angle(v: Array, ref: Array, axis: Array) -> float:
    return math.degrees(math.atan2(float(np.cross(ref, v) @ axis), float(v @ ref)))


def parameters_of(config: RigConfig, nominal: RigConfig) -> dict[str, float]:
    """The canonical parameters (deg or m) a configuration holds relative to its nominal;
    the inverse of :func:`apply_parameters`.

    Raises
    ------
    ParameterError
        When ``config`` holds an as-built term the parameters cannot express (a tilt axis
        turned in yaw, a stage offset in z, compliance of another joint than the tilt, a
        different light radius or servo set).
    """
    k0, n0, r0, w, u = _frame_vectors(nominal)
    g = config.geometry
    out: dict[str, float] = {}
    nom = {s.joint: s for s in nominal.servos}
    for s in config.servos:
        n = nom.get(s.joint)
        if n is None or (n.id, n.direction, n.gear_ratio) != (s.id, s.direction, s.gear_ratio):
            raise ParameterError(
                f"servo of {s.joint} (id {s.id}) differs from the nominal rig's in id, "
                "direction or gear ratio: not a calibration of this rig"
            )
        out[f"{s.joint}.offset"] = (n.zero_deg - s.zero_deg) / (s.direction * s.gear_ratio)
    for s in config.servos:
        out[f"{s.joint}.backlash"] = s.backlash_deg
        if s.joint != "stage_tilt" and any(c != 0 for c in s.compliance_deg):
            raise ParameterError(
                f"servo of {s.joint}: compliance_deg {list(s.compliance_deg)} is not a "
                "calibration parameter (only stage_tilt's gravity torque varies with its angle)"
            )
    out["stage_tilt.compliance_a"], out["stage_tilt.compliance_b"] = config.servo_for(
        "stage_tilt"
    ).compliance_deg
    out["light_elevation"] = g.light_elevation_deg
    out["camera_elevation"] = g.camera_elevation_deg
    out["camera_radius"] = g.camera_radius_m
    for a, m in zip("xyz", g.camera_mount_deg, strict=True):
        out[f"camera_mount_{a}"] = m
    k = normalize(np.asarray(g.tilt_axis, float))
    out["tilt_axis_pitch"] = _signed_angle(k, k0, w)
    n = normalize(np.asarray(g.rest_normal, float))
    out["spin_axis_yaw"] = _signed_angle(n, n0, u)
    for a, m in zip("xy", g.holder_tilt_deg, strict=True):
        out[f"holder_tilt_{a}"] = m
    for a, m in zip("xyz", g.holder_offset_m, strict=True):
        out[f"holder_offset_{a}"] = m
    out["stage_offset_x"], out["stage_offset_y"] = g.stage_offset_m[:2]
    # What the parameters cannot carry must match the nominal.
    back = apply_parameters(nominal, out, validate=False).geometry
    checks = {
        "tilt_axis": (k, np.asarray(back.tilt_axis)),
        "rest_normal": (n, np.asarray(back.rest_normal)),
        "rest_reference": (
            normalize(np.asarray(g.rest_reference, float)),
            np.asarray(back.rest_reference),
        ),
        "stage_offset_m": (np.asarray(g.stage_offset_m), np.asarray(back.stage_offset_m)),
        "light_radius_m": (np.asarray(g.light_radius_m), np.asarray(back.light_radius_m)),
    }
    for name, (a, b) in checks.items():
        if not np.allclose(a, b, rtol=0, atol=1e-9):
            raise ParameterError(
                f"geometry.{name} = {np.round(a, 9).tolist()} is not expressible by the "
                f"calibration parameters (nearest: {np.round(b, 9).tolist()})"
            )
    return out


# ------------------------------------------------------------------ camera
@dataclass(frozen=True)
class CameraPrior:
    """The camera calibration the rig calibration starts from.

    Attributes
    ----------
    K
        (3, 3) OpenCV camera matrix (px; pixel centres at integers).
    dist
        (5,) ``k1, k2, p1, p2, k3``.
    K_std
        (4,) standard deviations of ``fx, fy, cx, cy``, px.
    dist_std
        (5,) standard deviations of the distortion coefficients (0: held fixed).
    rms_px
        The camera calibration's reprojection RMS (the first guess of the corner noise).
    digest
        The camera calibration's digest of the camera's identity.
    width, height
        Image size, px (for the plan's visibility checks).
    covariance
        (9, 9) covariance of :meth:`vector` (the camera calibration's); None: the
        standard deviations alone, uncorrelated.  The intrinsics of a camera calibration
        are strongly correlated (fx with fy, k1 with k2, cx with p2), so a prior from
        the diagonal alone would hold some combinations far tighter than measured.
    """

    K: Array
    dist: Array
    K_std: Array
    dist_std: Array
    rms_px: float | None = None
    digest: str | None = None
    width: int | None = None
    height: int | None = None
    covariance: Array | None = None

    def prior_whitener(self) -> Array:
        """W with ``W (p - p_cal)`` the prior's residuals over the free intrinsics
        (std > 0): the inverse Cholesky factor of their covariance (``diag(1 / std)``
        without one)."""
        std = self.std_vector()
        free = np.flatnonzero(std > 0)
        if self.covariance is None:
            return np.diag(1.0 / std[free])
        cov = np.asarray(self.covariance, float)[np.ix_(free, free)]
        return np.linalg.inv(np.linalg.cholesky(cov))

    def vector(self) -> Array:
        """``fx, fy, cx, cy, k1, k2, p1, p2, k3``."""
        K = np.asarray(self.K, float)
        d = np.zeros(5)
        dd = np.asarray(self.dist, float).ravel()
        d[: min(5, dd.size)] = dd[:5]
        return np.concatenate([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], d])

    def std_vector(self) -> Array:
        """Standard deviations of :meth:`vector` (0: held fixed)."""
        ks = np.asarray(self.K_std, float)
        if ks.shape == (3, 3):
            ks = np.array([ks[0, 0], ks[1, 1], ks[0, 2], ks[1, 2]])
        d = np.zeros(5)
        ds = np.asarray(self.dist_std, float).ravel()
        d[: min(5, ds.size)] = ds[:5]
        return np.concatenate([ks.ravel()[:4], d])


def project_points(points_cam: ArrayLike, intrinsics: ArrayLike) -> Array:
    """OpenCV projection (Brown-Conrady distortion) of camera-frame points.

    Parameters
    ----------
    points_cam
        (..., 3) points in camera coordinates (x right, y down, z forward), m.
    intrinsics
        ``fx, fy, cx, cy`` (px) and ``k1, k2, p1, p2, k3``.

    Returns
    -------
    ndarray, (..., 2)
        Pixel coordinates (OpenCV: pixel centres at integers), what
        ``cv2.projectPoints`` gives.
    """
    p = np.asarray(points_cam, float)
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = np.asarray(intrinsics, float)
    x = p[..., 0] / p[..., 2]
    y = p[..., 1] / p[..., 2]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([fx * xd + cx, fy * yd + cy], axis=-1)


def _to_camera(rotation: Array, position: Array, points: Array) -> Array:
    """Sample-frame points into camera coordinates (``R^T (p - c)``), row-wise."""
    return np.einsum("nji,nj->ni", rotation, points - position)


# ------------------------------------------------------------------ the problem
def _validate(boards: Sequence[BoardObservation], spots: Sequence[SpotObservation]) -> None:
    """Refuse observations the model cannot use, naming the view and the field."""
    for o in [*boards, *spots]:
        missing = [j for j in JOINT_NAMES if j not in o.joints]
        if missing:
            raise CalibrationError(
                f"{o.label}: joints lack {missing}; expected all of {JOINT_NAMES}"
            )
        if not all(math.isfinite(float(o.joints[j])) for j in JOINT_NAMES):
            raise CalibrationError(f"{o.label}: joints {dict(o.joints)} are not all finite")
    for b in boards:
        op = np.asarray(b.object_points, float)
        ip = np.asarray(b.image_points, float)
        if op.ndim != 2 or op.shape[1] != 3 or ip.shape != (len(op), 2) or len(op) == 0:
            raise CalibrationError(
                f"{b.label}: object_points {op.shape} and image_points {ip.shape} must be "
                "(n, 3) and (n, 2) with n > 0"
            )
        if not (np.all(np.isfinite(op)) and np.all(np.isfinite(ip))):
            raise CalibrationError(f"{b.label}: corner coordinates are not all finite")
    for s in spots:
        ip = np.asarray(s.image_point, float)
        if ip.shape != (2,) or not np.all(np.isfinite(ip)):
            raise CalibrationError(f"{s.label}: image_point {ip.tolist()} is not 2 finite px")


class _Problem:
    """Observations as arrays, and the model's prediction of them for a parameter vector."""

    def __init__(
        self,
        nominal: RigConfig,
        boards: Sequence[BoardObservation],
        spots: Sequence[SpotObservation],
        camera: CameraPrior,
    ) -> None:
        self.nominal = nominal
        self.frames = _frame_vectors(nominal)
        self.boards = list(boards)
        self.spots = list(spots)
        obs = [*self.boards, *self.spots]
        _validate(self.boards, self.spots)
        self.joints = {j: np.array([o.joints[j] for o in obs], float) for j in JOINT_NAMES}
        self.approach = {
            j: np.array([float(o.approach.get(j, 0)) for o in obs]) for j in JOINT_NAMES
        }
        nb = len(self.boards)
        self.n_boards = nb
        pts = [np.asarray(b.object_points, float).reshape(-1, 3) for b in self.boards]
        img = [np.asarray(b.image_points, float).reshape(-1, 2) for b in self.boards]
        self.view_of_corner = np.concatenate(
            [np.full(len(p), i) for i, p in enumerate(pts)] or [np.zeros(0, int)]
        ).astype(int)
        self.object_points = np.concatenate(pts) if pts else np.zeros((0, 3))
        self.image_points = np.concatenate(img) if img else np.zeros((0, 2))
        self.spot_points = (
            np.array([np.asarray(s.image_point, float).reshape(2) for s in self.spots])
            if self.spots
            else np.zeros((0, 2))
        )
        self.names = list(PARAMETER_NAMES)
        self.x0_rig = np.array([_nominal_values(nominal)[n] for n in self.names])
        prior, prior_std = camera.vector(), camera.std_vector()
        self.free_intrinsics = np.flatnonzero(prior_std > 0)
        self.prior = prior
        self.prior_std = prior_std
        self.prior_whitener = camera.prior_whitener()
        self.names += [INTRINSIC_NAMES[i] for i in self.free_intrinsics]
        self.x0 = np.concatenate([self.x0_rig, prior[self.free_intrinsics]])
        self.scale = np.concatenate(
            [[PARAMETERS[n].magnitude for n in PARAMETER_NAMES], prior_std[self.free_intrinsics]]
        )
        self.n_rig = len(PARAMETER_NAMES)

    # -- model
    def intrinsics(self, x: Array) -> Array:
        k = self.prior.copy()
        k[self.free_intrinsics] = x[self.n_rig :]
        return k

    def poses(self, x: Array) -> tuple[Array, Array, Array]:
        """(camera rotations (V, 3, 3), camera positions (V, 3), mirrored light centres
        (S, 3)) in the sample frame for the rig part of ``x``."""
        values = dict(zip(PARAMETER_NAMES, x[: self.n_rig], strict=True))
        config = apply_parameters(self.nominal, values, validate=False, _frames=self.frames)
        joints = {j: self.joints[j] + math.radians(values[f"{j}.offset"]) for j in JOINT_NAMES}
        poses = rig_poses(config, joints, self.approach)
        lp = poses.light_position[self.n_boards :] * np.array([1.0, 1.0, -1.0])
        return poses.camera_rotation, poses.camera_position, lp

    def project(self, poses: tuple[Array, Array, Array], intr: Array) -> Array:
        """Raw residuals (corners then spots, flattened), px."""
        R, C, lp = poses
        nb, idx = self.n_boards, self.view_of_corner
        corners = project_points(_to_camera(R[idx], C[idx], self.object_points), intr)
        spots = project_points(_to_camera(R[nb:], C[nb:], lp), intr)
        return np.concatenate(
            [(corners - self.image_points).ravel(), (spots - self.spot_points).ravel()]
        )

    def raw_residuals(self, x: Array) -> tuple[Array, Array]:
        """(corner residuals (N, 2), spot residuals (S, 2)), px."""
        r = self.project(self.poses(x), self.intrinsics(x))
        nc = 2 * len(self.image_points)
        return r[:nc].reshape(-1, 2), r[nc:].reshape(-1, 2)

    def row_weights(self, sigma_board: float, sigma_spot: float) -> Array:
        nc, ns = 2 * len(self.image_points), 2 * len(self.spot_points)
        return np.concatenate([np.full(nc, 1 / sigma_board), np.full(ns, 1 / sigma_spot)])

    def weighted(self, x: Array, sigma_board: float, sigma_spot: float) -> Array:
        r = self.project(self.poses(x), self.intrinsics(x))
        free = self.free_intrinsics
        prior = self.prior_whitener @ (x[self.n_rig :] - self.prior[free])
        return np.concatenate([r * self.row_weights(sigma_board, sigma_spot), prior])

    def raw_jacobian(self, x: Array) -> Array:
        """Jacobian of the raw residuals (px per parameter unit): forward differences,
        steps of 1e-3 of each parameter's scale; the intrinsics' columns reuse the poses."""
        poses = self.poses(x)
        intr = self.intrinsics(x)
        r0 = self.project(poses, intr)
        cols = []
        for i, h in enumerate(1e-3 * self.scale):
            xp = x.copy()
            xp[i] += h
            if i < self.n_rig:
                cols.append((self.project(self.poses(xp), intr) - r0) / h)
            else:
                cols.append((self.project(poses, self.intrinsics(xp)) - r0) / h)
        return np.stack(cols, axis=1)

    def jacobian(self, x: Array, sigma_board: float, sigma_spot: float) -> Array:
        """Jacobian of :meth:`weighted`."""
        return self.weight_jacobian(self.raw_jacobian(x), sigma_board, sigma_spot)

    def weight_jacobian(self, raw: Array, sigma_board: float, sigma_spot: float) -> Array:
        nfree = len(self.free_intrinsics)
        prior = np.zeros((nfree, raw.shape[1]))
        prior[:, self.n_rig :] = self.prior_whitener
        return np.vstack([raw * self.row_weights(sigma_board, sigma_spot)[:, None], prior])

    def row_clusters(self) -> Array:
        """The independent error each data row belongs to: a board view's corners share
        one (its index), each mirror spot is its own (``n_boards + k``); prior rows -1."""
        spots = self.n_boards + np.arange(len(self.spot_points))
        prior = np.full(len(self.free_intrinsics), -1)
        return np.concatenate([np.repeat(self.view_of_corner, 2), np.repeat(spots, 2), prior])

    def kind_rows(self) -> tuple[slice, slice, slice]:
        nb, ns = 2 * len(self.image_points), 2 * len(self.spot_points)
        return slice(0, nb), slice(nb, nb + ns), slice(nb + ns, None)


# ------------------------------------------------------------------ observability
@dataclass(frozen=True)
class Observability:
    """Predicted standard deviations of the parameters (deg or m) and the refused ones.

    Attributes
    ----------
    std
        Parameter name -> predicted std (inf when the observations do not determine it).
    refused
        Parameter name -> why (what the plan or the observations lack).
    """

    std: dict[str, float]
    refused: dict[str, str]

    def raise_if_refused(self, what: str = "the calibration") -> None:
        """Raise :class:`CalibrationError` naming every refused parameter."""
        if self.refused:
            lines = "\n".join(f"  {n}: {why}" for n, why in self.refused.items())
            raise CalibrationError(
                f"{what} cannot determine {len(self.refused)} parameter(s):\n{lines}"
            )


def _covariance(jw: Array, scale: Array) -> tuple[Array, Array]:
    """(covariance in parameter units, eigenvalues of the scaled normal matrix).

    From the eigen-decomposition of the (small) normal matrix of the scaled Jacobian; a
    direction the data do not fix (an eigenvalue below 1e-14 of the largest: a singular
    value below 1e-7) makes every parameter taking part in it unbounded (inf)."""
    js = jw * scale
    ev, vec = np.linalg.eigh(js.T @ js)
    good = ev > ev.max() * 1e-14
    cov_s = (vec[:, good] / ev[good]) @ vec[:, good].T
    if not good.all():
        null = np.abs(vec[:, ~good]).max(axis=1) > 1e-3
        cov_s[null, :] = np.inf
        cov_s[:, null] = np.inf
    return cov_s * np.outer(scale, scale), ev


def _view_correlated(cov: Array, jw: Array, r: Array, clusters: Array) -> Array:
    """The covariance with errors shared by the corners of a view: each parameter's
    variance raised to the view-clustered sandwich's ``[cov (sum_v g_v g_v^T) cov]_ii``
    where that is larger (``g_v = J_v^T r_v`` over the weighted rows of view v; prior
    rows ``J_p^T J_p``), the correlations of ``cov`` kept.

    Why: ``(J^T W J)^-1`` takes every corner's error as independent, but a view's corners
    move together (its detection, its board pose), and on 20 simulated as-built worlds
    the parameters' z-scores had an RMS of 1.23 (14 of 660 beyond 3 sigma; the spin's
    backlash and axis yaw 1.6-1.7); with the views' shared errors 1.05 (2 of 660).  The
    sandwich's small-sample factor is ``G / (G - 1) (N - 1) / (N - P)`` (G clusters, N
    data rows, P parameters)."""
    finite = np.isfinite(np.diag(cov))
    if not finite.any():
        return cov
    data = clusters >= 0
    ids, inv = np.unique(clusters[data], return_inverse=True)
    n_rows, n_par = int(data.sum()), int(finite.sum())
    if ids.size < 2 or n_rows <= n_par:
        return cov
    jf = jw[:, finite]
    g = np.zeros((ids.size, n_par))
    np.add.at(g, inv, jf[data] * r[data, None])
    factor = ids.size / (ids.size - 1) * (n_rows - 1) / (n_rows - n_par)
    meat = factor * (g.T @ g) + jf[~data].T @ jf[~data]
    c = cov[np.ix_(finite, finite)]
    sandwich_var = np.einsum("ij,jk,ki->i", c, meat, c)
    # Each parameter's std raised to the sandwich's, the correlations kept (D cov D stays
    # positive semi-definite).  The positive part of (sandwich - cov) as a matrix was
    # tried: with ~100 views for ~40 parameters the difference's eigenvalues are noisy
    # and keeping only the positive ones doubled the holder offsets' std where the
    # corners' errors are independent.
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.sqrt(np.maximum(sandwich_var / np.diag(c), 1.0))
    d = np.where(np.isfinite(d), d, 1.0)
    out = cov.copy()
    out[np.ix_(finite, finite)] = c * np.outer(d, d)
    return out


def _why(name: str, std: float, problem: _Problem, cov: Array) -> str:
    spec = PARAMETERS[name]
    joint = name.split(".")[0]
    if name.endswith(".backlash"):
        obs = problem.spots if joint == "light_azimuth" else [*problem.boards, *problem.spots]
        signs = {int(np.sign(o.approach.get(joint, 0))) for o in obs} - {0}
        if len(signs) < 2:
            side = {1: "increasing", -1: "decreasing"}.get(next(iter(signs), 0), "an unknown")
            return (
                f"every pose approaches {joint} from the same side ({side} angle); the plan "
                "needs poses approached from both sides"
            )
    if name in _LIGHT_PARAMETERS and len(problem.spots) < MIN_MIRROR_VIEWS:
        return (
            f"only {len(problem.spots)} mirror view(s): the light's parameters "
            f"({', '.join(_LIGHT_PARAMETERS)}) need at least {MIN_MIRROR_VIEWS} mirror views at "
            "several light azimuths and tilts, approached from both sides"
        )
    if not math.isfinite(std):
        return (
            "the observations do not determine it at all (it moves no corner or spot "
            "independently of the other parameters); the plan needs poses that vary it"
        )
    i = problem.names.index(name)
    d = np.sqrt(np.diag(cov))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov[i] / (d[i] * d)
    corr[i] = 0.0
    corr = np.where(np.isfinite(corr), corr, 0.0)
    j = int(np.argmax(np.abs(corr)))
    return (
        f"its standard deviation would be {std:.3g} {spec.unit} against an expected "
        f"magnitude of {spec.magnitude:g} {spec.unit}; the plan's poses hardly separate it "
        f"from {problem.names[j]} (correlation {corr[j]:+.3f})"
    )


def _judge(problem: _Problem, cov: Array) -> Observability:
    std = {}
    refused = {}
    for i, name in enumerate(PARAMETER_NAMES):
        sd = float(np.sqrt(cov[i, i])) if np.isfinite(cov[i, i]) else math.inf
        std[name] = sd
        if not sd <= OBSERVABLE_FRACTION * PARAMETERS[name].magnitude:
            refused[name] = _why(name, sd, problem, cov)
    return Observability(std, refused)


def observability(
    nominal: RigConfig,
    boards: Sequence[BoardObservation],
    spots: Sequence[SpotObservation],
    camera: CameraPrior,
    *,
    sigma_board_px: float | None = None,
    sigma_spot_px: float | None = None,
) -> Observability:
    """Which parameters the observations would determine, judged at the nominal rig.

    Parameters
    ----------
    nominal
        The rig as drawn.
    boards, spots
        The observations (or a plan's predicted ones, :mod:`gonio.rig.calibration_plan`).
    camera
        The camera calibration (intrinsics and their uncertainty).
    sigma_board_px, sigma_spot_px
        Expected corner and spot noise, px (default: the camera calibration's RMS, else
        0.3 px).
    """
    problem = _Problem(nominal, boards, spots, camera)
    guess = camera.rms_px or 0.3
    jw = problem.jacobian(problem.x0, sigma_board_px or guess, sigma_spot_px or guess)
    cov, _ = _covariance(jw, problem.scale)
    if len(problem.spots) < MIN_MIRROR_VIEWS:
        light = [PARAMETER_NAMES.index(n) for n in _LIGHT_PARAMETERS]
        cov[light, :] = np.inf
        cov[:, light] = np.inf
    return _judge(problem, cov)


# ------------------------------------------------------------------ the solve
@dataclass(frozen=True)
class ViewResidual:
    """One view's residuals after the fit: kind (``"board"``/``"spot"``), count of points,
    RMS and largest point distance, px."""

    label: str
    kind: str
    n: int
    rms_px: float
    max_px: float


@dataclass
class RigCalibration:
    """A solved rig calibration.

    Attributes
    ----------
    config
        The calibrated rig configuration (its ``calibration`` record set).
    names
        Parameter names of the fitted vector: :data:`PARAMETER_NAMES` then the free
        intrinsics.
    values, std
        Estimates and standard deviations in the parameters' units.
    covariance, correlation
        Of the fitted vector.
    sigma_px
        Noise per observation kind (``"board"``, ``"spot"``) from the residuals and the
        degrees of freedom, px.
    rms_px
        Residual RMS per kind (per coordinate), px.
    views
        Residuals of every view kept.
    rejected
        Label -> why (views left out).
    ill_conditioned
        Parameter name -> why (non-empty: no calibrated file is written).
    solve_time_s, nfev
        Wall time of the solves and model evaluations.
    """

    config: RigConfig
    names: list[str]
    values: Array
    std: Array
    covariance: Array
    correlation: Array
    sigma_px: dict[str, float]
    rms_px: dict[str, float]
    views: list[ViewResidual]
    rejected: dict[str, str]
    ill_conditioned: dict[str, str]
    solve_time_s: float
    nfev: int
    record: CalibrationRecord
    estimates: dict[str, tuple[float, float]] = field(default_factory=dict)

    def estimate(self, name: str) -> tuple[float, float]:
        """``(value, std)`` of a parameter (canonical or intrinsic name)."""
        i = self.names.index(name)
        return float(self.values[i]), float(self.std[i])


def _solve(problem: _Problem, x0: Array, sb: float, ss: float) -> tuple[Array, int]:
    from scipy.optimize import least_squares

    res = least_squares(
        problem.weighted,
        x0,
        jac=problem.jacobian,
        args=(sb, ss),
        method="lm",
        x_scale=problem.scale,
        xtol=1e-12,
        ftol=1e-12,
        gtol=1e-12,
        max_nfev=100,
    )
    return res.x, int(res.nfev)


def _sigmas(
    problem: _Problem, x: Array, sb: float, ss: float
) -> tuple[float, float, Array, Array]:
    """Per-kind sigma from the residuals and the degrees of freedom each kind used (the
    hat matrix' trace over its rows), the raw Jacobian at ``x`` and the rows' leverage."""
    raw = problem.raw_jacobian(x)
    jw = problem.weight_jacobian(raw, sb, ss)
    r = problem.weighted(x, sb, ss)
    leverage = np.einsum("ij,ij->i", jw @ np.linalg.pinv(jw.T @ jw), jw)
    b, s, _ = problem.kind_rows()
    out = []
    for rows, sigma in ((b, sb), (s, ss)):
        n = r[rows].size
        dof = n - leverage[rows].sum()
        out.append(sigma * math.sqrt(float(r[rows] @ r[rows]) / dof) if n and dof > 0.5 else sigma)
    return out[0], out[1], raw, leverage


def _view_residuals(
    problem: _Problem, x: Array, leverage: Array | None = None
) -> list[ViewResidual]:
    """Each view's residuals, px; with ``leverage`` (the rows' hat-matrix diagonal)
    studentized, r / sqrt(1 - h): a view that alone pins some parameters (few spots for
    the light's three) is fitted closely, and its raw residual would understate how far
    it is from the rest, and shrink the median the others are judged by."""
    rb, rs = problem.raw_residuals(x)
    if leverage is not None:
        b, s, _ = problem.kind_rows()
        stud = 1.0 / np.sqrt(np.clip(1.0 - leverage, 1e-3, None))
        rb = rb * stud[b].reshape(-1, 2)
        rs = rs * stud[s].reshape(-1, 2)
    out = []
    d = np.hypot(rb[:, 0], rb[:, 1])
    for i, b in enumerate(problem.boards):
        di = d[problem.view_of_corner == i]
        out.append(
            ViewResidual(
                b.label, "board", di.size, float(np.sqrt(np.mean(di**2) / 2)), float(di.max())
            )
        )
    for s, r in zip(problem.spots, rs, strict=True):
        e = float(np.hypot(*r))
        out.append(ViewResidual(s.label, "spot", 1, e / math.sqrt(2), e))
    return out


def _outliers(views: list[ViewResidual]) -> dict[tuple[str, str], str]:
    """(kind, label) -> why, for the views whose (studentized) RMS exceeds REJECT_FACTOR x
    their kind's median (a board and a spot of the same pose are judged apart)."""
    out = {}
    for kind in ("board", "spot"):
        vs = [v for v in views if v.kind == kind]
        if len(vs) < 3:
            continue
        med = float(np.median([v.rms_px for v in vs]))
        for v in vs:
            if v.rms_px > REJECT_FACTOR * med:
                out[(kind, v.label)] = (
                    f"{kind} studentized residual RMS {v.rms_px:.3g} px > "
                    f"{REJECT_FACTOR:g} x the median {med:.3g} px"
                )
    return out


def calibrate_rig(
    nominal: RigConfig,
    boards: Sequence[BoardObservation],
    spots: Sequence[SpotObservation],
    camera: CameraPrior,
    *,
    camera_digest: str | None = None,
    check: bool = True,
) -> RigCalibration:
    """Solve the as-built parameters of ``nominal`` from board views and mirror spots.

    Parameters
    ----------
    nominal
        The rig as drawn (the observations' ``joints`` are its encoder readings, rad).
    boards, spots
        The observations (:mod:`gonio.rig.calibration_data`).
    camera
        The camera calibration: intrinsics and their standard deviations (priors).
    camera_digest
        The camera's identity digest, recorded (default ``camera.digest``).
    check
        Refuse before solving when the observations leave a parameter unobservable.

    Returns
    -------
    RigCalibration
        With ``ill_conditioned`` naming parameters the solution does not determine
        (:func:`write_calibrated_rig` then refuses).

    Raises
    ------
    CalibrationError
        Too few views, or (``check``) a parameter the observations cannot determine.
    """
    if len(boards) < MIN_BOARD_VIEWS:
        raise CalibrationError(
            f"{len(boards)} board view(s): a rig calibration needs at least {MIN_BOARD_VIEWS} "
            "(the camera arm and the stage are told apart by many views)"
        )
    t0 = time.perf_counter()
    boards, spots = list(boards), list(spots)
    if check:
        observability(nominal, boards, spots, camera).raise_if_refused(
            "the calibration observations"
        )
    sb = ss = camera.rms_px or 0.3
    rejected: dict[str, str] = {}
    nfev = 0
    x = None
    for _ in range(10):
        problem = _Problem(nominal, boards, spots, camera)
        x = problem.x0 if x is None else x
        for _ in range(2):  # the weights, iterated once on the first solve's residuals
            x, n = _solve(problem, x, sb, ss)
            nfev += n
            sb, ss, raw, leverage = _sigmas(problem, x, sb, ss)
        bad = _outliers(_view_residuals(problem, x, leverage))
        if not bad:
            break
        rejected.update({f"{kind} {label}": why for (kind, label), why in bad.items()})
        boards = [b for b in boards if ("board", b.label) not in bad]
        spots = [s for s in spots if ("spot", s.label) not in bad]
        if len(boards) < MIN_BOARD_VIEWS:
            raise CalibrationError(
                f"after rejecting {len(rejected)} view(s) only {len(boards)} board views remain "
                f"(need {MIN_BOARD_VIEWS}): {rejected}"
            )
    jw = problem.weight_jacobian(raw, sb, ss)
    cov, _ = _covariance(jw, problem.scale)
    cov = _view_correlated(cov, jw, problem.weighted(x, sb, ss), problem.row_clusters())
    std = np.sqrt(np.where(np.isfinite(np.diag(cov)), np.diag(cov), np.inf))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(std, std)
    judged = _judge(problem, cov)
    views = _view_residuals(problem, x)
    rb, rs = problem.raw_residuals(x)
    rms = {"board": float(np.sqrt(np.mean(rb**2)))}
    if rs.size:
        rms["spot"] = float(np.sqrt(np.mean(rs**2)))
    values = dict(zip(PARAMETER_NAMES, x[: problem.n_rig], strict=True))
    params = {
        n: ParameterEstimate(value=float(values[n]), std=float(std[i]), unit=PARAMETERS[n].unit)
        for i, n in enumerate(PARAMETER_NAMES)
        if np.isfinite(std[i])
    }
    intr = {
        name: ParameterEstimate(
            value=float(x[i]), std=float(std[i]), unit=_INTRINSIC_UNITS[INTRINSIC_NAMES.index(name)]
        )
        for i, name in enumerate(problem.names)
        if i >= problem.n_rig and np.isfinite(std[i])
    }
    record = CalibrationRecord(
        created=datetime.now(UTC).isoformat(timespec="seconds"),
        nominal_digest=rig_digest(nominal),
        camera_digest=camera_digest if camera_digest is not None else camera.digest,
        rms_px=rms,
        counts={
            "board_views": len(boards),
            "board_corners": int(len(problem.image_points)),
            "spots": len(spots),
            "rejected": len(rejected),
        },
        parameters=params,
        intrinsics=intr,
        rejected=rejected,
        not_observable=dict(NOT_OBSERVABLE),
        covariance=_covariance_record(problem.names, cov, std),
        # exclude_none: the record is written into the rig TOML, which has no null
        nominal=nominal.model_dump(mode="json", exclude={"calibration"}, exclude_none=True),
    )
    # The configuration cannot hold a negative backlash: an estimate below 0 is one
    # consistent with none (its raw value stays in the record).
    cfg_values = dict(values)
    for j in JOINT_NAMES:
        cfg_values[f"{j}.backlash"] = max(0.0, cfg_values[f"{j}.backlash"])
    config = apply_parameters(nominal, cfg_values, validate=False).model_copy(
        update={"calibration": record}
    )
    return RigCalibration(
        config=config,
        names=problem.names,
        values=x,
        std=std,
        covariance=cov,
        correlation=corr,
        sigma_px={"board": sb, "spot": ss},
        rms_px=rms,
        views=views,
        rejected=rejected,
        ill_conditioned=judged.refused,
        solve_time_s=time.perf_counter() - t0,
        nfev=nfev,
        record=record,
        estimates={n: (float(x[i]), float(std[i])) for i, n in enumerate(problem.names)},
    )


def _covariance_record(names: Sequence[str], cov: Array, std: Array) -> ParameterCovariance:
    """The record's covariance table over the parameters with a finite std (the others
    are not in the record's estimates either); exactly symmetric, as TOML keeps it."""
    keep = np.flatnonzero(np.isfinite(std))
    sub = cov[np.ix_(keep, keep)]
    sub = 0.5 * (sub + sub.T)
    return ParameterCovariance(
        names=[names[i] for i in keep], matrix=[[float(v) for v in row] for row in sub]
    )


# ------------------------------------------------------------------ the file
_HEADER = (
    "# A calibrated rig configuration written by `gonio calibrate rig` ({created}).\n"
    "# The as-built fields (zero_deg, backlash_deg, compliance_deg, elevations, camera\n"
    "# radius and mount, tilt axis, rest orientation, holder tilt and offset, stage offset)\n"
    "# are the calibration's estimates; [calibration] holds their standard deviations, the\n"
    "# residuals and the digests of the nominal rig and camera it was made for.\n"
    "# Use it with --rig; recalibrate from the nominal configuration when the rig changes.\n"
)


def write_calibrated_rig(
    path: str | Path, calibration: RigCalibration, *, force: bool = False
) -> Path:
    """Write the calibrated rig configuration (a full rig TOML ``load_rig_config`` reads).

    Raises
    ------
    CalibrationError
        When the fit is ill-conditioned (naming the parameters), or ``path`` exists and
        ``force`` is false.  Nothing is written then.
    """
    import tomli_w

    from gonio.atomic import atomic_path

    path = Path(path)
    if calibration.ill_conditioned:
        lines = "\n".join(f"  {n}: {w}" for n, w in calibration.ill_conditioned.items())
        raise CalibrationError(
            f"not writing {path}: the fit is ill-conditioned for "
            f"{len(calibration.ill_conditioned)} parameter(s):\n{lines}"
        )
    if path.exists() and not force:
        raise CalibrationError(f"{path} exists; not overwritten (use --force to replace it)")
    data = calibration.config.model_dump(mode="json", exclude_none=True)
    rig_config_from_dict(data, str(path))  # what is written must load
    text = _HEADER.format(created=calibration.record.created) + tomli_w.dumps(data)
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path
