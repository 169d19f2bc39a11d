"""Kinematics of the gonioreflectometer: joint angles <-> light and camera directions.

Geometry kind ``arms_tilt_spin`` (the default preset, see :class:`GeometryConfig`)
-------------------------------------------------------------------------------------
World frame: origin at the sample centre, +z up.  The light arm and the camera arm turn
about the world z axis; an arm at azimuth ``a`` and elevation ``e`` holds its device in
direction ``d(a, e) = (cos e cos a, cos e sin a, sin e)`` from the sample centre.  The
stage maps sample coordinates to world coordinates with ``M = A(tilt) @ B @ Rz(spin)``:
``Rz`` spins about the sample normal, ``B`` is the rest orientation (sample normal along
``rest_normal``, sample +x along ``rest_reference``), ``A`` turns about the horizontal
``tilt_axis``.  Then ``wi = M.T @ d(a_light, e_light)`` and ``wo = M.T @ d(a_cam, e_cam)``.

Inverse.  Let ``u = M.T @ z`` be the world's up direction seen in the sample frame.  Both
devices sit at fixed elevations, so ``u . wi = sin e_light`` and ``u . wo = sin e_cam``:
``u = alpha wi + beta wo + gamma (wi x wo)`` with ``(alpha, beta)`` from a 2x2 linear system
and ``gamma = +-sqrt(1 - |alpha wi + beta wo|^2) / |wi x wo|`` -- two mirror solutions
(light left or right of the camera).  ``u`` fixes the tilt (from ``u_z``, two branches) and
the spin (from the azimuth of ``u``); the arm azimuths then follow from ``M wi`` and
``M wo``.  With both elevations 0 the in-plane configurations (``phi_o = phi_i + pi``)
have ``u`` along the sample y axis, i.e. tilt = 0; out-of-plane configurations tilt the
stage.  Four joints give four degrees of freedom, so every pair (wi, wo) -- isotropic
and anisotropic -- is reached, except when wi and wo are parallel (the devices would
have to be in the same place).

Every solution (both mirrors, both tilt branches, every 2 pi turn within the limits) is
checked against joint limits, the holder rim (``max_theta_deg``), the camera-shadow
condition (angular separation of light and camera seen from the sample below
``min_separation_deg`` or below what the devices' bodies subtend) and arm-arm
clearance, and -- when the arms cannot pass each other -- that the move keeps the arms'
order and clearance along the servos' trapezoid profiles.  The survivor with the
shortest move time wins.

As built.  A calibrated configuration (backlash, compliance, camera mount, holder tilt
and offset, stage offset, a tilt axis a little off horizontal) is modelled by
:func:`gonio.rig.asbuilt.rig_poses`; ``forward`` and ``poses`` then use it (directions
from the sample centre, the joints' approach signs taken into account).  A nominal
configuration (every as-built term zero, tilt axis horizontal) keeps the closed form
above, bit for bit.  The inverse of an as-built rig solves the closed form of its
nominal part (tilt axis made horizontal, no offsets) and refines every candidate with
Gauss-Newton steps on the full model (4 joints, 4 constraints) until ``wi`` and ``wo``
are met to ``1e-9`` rad, with the approach signs the move from ``current`` implies: a
joint that moves by more than the position tolerance (the servo's deadband) approaches
from the side it comes from, one that does not keeps its sign (``approach``; unknown
counts as +1, the side the rig's first move takes the backlash up from, see
:class:`gonio.rig.device.Rig`).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gonio.errors import ConfigError, PoseRefused, RefusalReason, RigError
from gonio.radiometry.frames import angle_between, look_along_rotation, normalize, rotation_about
from gonio.rig import asbuilt
from gonio.rig.config import JOINT_NAMES, RigConfig, ServoConfig
from gonio.rig.control_table import (
    MODELS,
    acceleration_register,
    profile_pulses,
    velocity_register,
)

Array = NDArray[np.float64]
Joints = Mapping[str, float]

_Z = np.array([0.0, 0.0, 1.0])
_EPS = 1e-12
#: How closely the as-built inverse meets the requested directions, rad.
_REFINE_TOL = 1e-9
_REFINE_STEPS = 12
#: Central-difference step of the refinement's Jacobian, rad (error ~ h^2 ~ 1e-12).
_JAC_STEP = 1e-6


def is_nominal(config: RigConfig) -> bool:
    """Whether every as-built term of ``config`` is zero and its tilt axis horizontal
    (the closed-form kinematics is then exact)."""
    g = config.geometry
    return (
        g.tilt_axis[2] == 0.0
        and not any(g.camera_mount_deg)
        and not any(g.holder_tilt_deg)
        and not any(g.holder_offset_m)
        and not any(g.stage_offset_m)
        and all(s.backlash_deg == 0.0 and not any(s.compliance_deg) for s in config.servos)
    )


#: The backlash an uncalibrated rig's controller assumes when its configuration states
#: none (deg): twice the XM430's datasheet 15 arcmin.  A nominal rig.toml says 0 because
#: nobody has measured it yet, not because the gears have no play: taking that at its
#: word let a 2-pulse reversal during the rig calibration's own session be journaled as
#: a side change the gears never made (world 3104: the spin's backlash read 6 sigma low).
UNCALIBRATED_BACKLASH_DEG = 0.5


def take_up_servo(servo: ServoConfig, config: RigConfig) -> ServoConfig:
    """``servo`` as the controller's take-up rules see it: a rig without a calibration
    record whose servo states no backlash is given :data:`UNCALIBRATED_BACKLASH_DEG`
    (for the pre-move decisions only, never in the kinematics)."""
    if config.calibration is None and servo.backlash_deg <= 0.0:
        return servo.model_copy(update={"backlash_deg": UNCALIBRATED_BACKLASH_DEG})
    return servo


def take_up_pulses(servo: ServoConfig, tol: int) -> int:
    """The shortest reversal (pulses) that surely carries ``servo``'s joint across its
    backlash: the play in pulses, rounded up, plus the deadband ``tol`` it may land
    short by.  Equal to ``tol`` for a servo without backlash (every move counts)."""
    play = servo.backlash_deg / 360.0 * 4096.0 * servo.gear_ratio
    return int(math.ceil(play - 1e-9)) + int(tol)


def pre_move_side(
    servo: ServoConfig, d_pulses: ArrayLike, side: int, tol: int
) -> NDArray[np.float64]:
    """The side (+1, -1 in joint angle) from which :class:`gonio.rig.device.Rig`
    approaches the goal of a move of ``d_pulses`` (goal minus present) through a
    pre-move, 0 where the move itself leaves a known side.

    A joint with backlash needs one when its move is no longer than
    :func:`take_up_pulses`: from an unknown side (``side`` 0) it comes from below (+1),
    and a reversal of a known side that short would stop the gears inside their play
    (the encoder moved, the joint did not, or only partly), so it comes from that side.
    A move within the deadband (``|d| <= tol``) does not move a known side's servo.
    """
    d = np.asarray(d_pulses, dtype=np.float64)
    if servo.backlash_deg <= 0:
        return np.zeros_like(d)
    short = np.abs(d) <= take_up_pulses(servo, tol)
    if side == 0:
        return np.where(short, 1.0, 0.0)
    reverses = (np.abs(d) > tol) & (servo.direction * np.sign(d) != side)
    return np.where(short & reverses, float(side), 0.0)


def side_after(servo: ServoConfig, d_pulses: ArrayLike, side: int, tol: int) -> NDArray[np.float64]:
    """Approach sign(s) a move of ``d_pulses`` (goal minus present) leaves, from ``side``
    (+1, -1 in joint angle; 0 unknown).

    A move within the deadband (``|d| <= tol``) does not move the servo: the side stays.
    A move that needs a pre-move (:func:`pre_move_side`) ends on the pre-move's side.
    Any other move takes the sign of its change in joint angle.
    """
    d = np.asarray(d_pulses, dtype=np.float64)
    plain = np.where(np.abs(d) > tol, servo.direction * np.sign(d), float(side))
    pre = pre_move_side(servo, d, side, tol)
    return np.where(pre != 0, pre, plain)


def approach_of_move(
    config: RigConfig,
    joints_from: Joints,
    joints_to: Joints,
    approach: Mapping[str, int] | None = None,
) -> dict[str, int]:
    """Approach signs after moving from ``joints_from`` to ``joints_to`` (rad).

    :func:`side_after` of each joint's change in pulses, from ``approach`` (0 unknown
    when None or absent): a joint whose goal changes by more than
    ``motion.position_tolerance_pulses`` takes the sign of its change in joint angle,
    unless it is a reversal shorter than the backlash (approached from the present side);
    one that does not keeps its sign (:meth:`gonio.rig.device.Rig` moves by the same
    rule).
    """
    out = {}
    tol = config.motion.position_tolerance_pulses
    for s in config.servos:
        j = s.joint
        d = round(s.pulses(float(joints_to[j]))) - round(s.pulses(float(joints_from[j])))
        out[j] = int(side_after(take_up_servo(s, config), d, int((approach or {}).get(j, 0)), tol))
    return out


def _wrap(a: ArrayLike) -> Array:
    """Angle wrapped to (-pi, pi]."""
    return -np.remainder(-np.asarray(a, dtype=np.float64) + np.pi, 2 * np.pi) + np.pi


def trapezoid_time(distance: ArrayLike, speed: ArrayLike, accel: ArrayLike) -> Array:
    """Duration (s) of a rest-to-rest trapezoid move.

    Parameters
    ----------
    distance
        Path length (any unit u), >= 0.
    speed, accel
        Cruise speed (u/s, > 0) and acceleration (u/s^2, may be ``inf``).
    """
    d = np.abs(np.asarray(distance, dtype=np.float64))
    v = np.asarray(speed, dtype=np.float64)
    a = np.asarray(accel, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        ramp = np.where(np.isinf(a), 0.0, v * v / a)  # distance to reach v and stop again
        t_full = d / v + np.where(np.isinf(a), 0.0, v / a)
        t_tri = 2.0 * np.sqrt(d / a)
    return np.where(d >= ramp, t_full, t_tri)


def _trapezoid_time_scalar(d: float, v: float, a: float) -> float:
    # scalar twin of trapezoid_time: move_time runs inside the inverse's candidate loop
    d = abs(d)
    if math.isinf(a):
        return d / v
    if d >= v * v / a:
        return d / v + v / a
    return 2.0 * math.sqrt(d / a)


def trapezoid_position(distance: float, speed: float, accel: float, t: ArrayLike) -> Array:
    """Distance covered at time ``t`` (s) along the move of :func:`trapezoid_time`."""
    t = np.asarray(t, dtype=np.float64)
    d = abs(distance)
    if d == 0:
        return np.zeros_like(t)
    if math.isinf(accel):
        return np.clip(t * speed, 0.0, d)
    v = min(speed, math.sqrt(d * accel))  # peak speed (triangle when the cruise is never reached)
    t_acc = v / accel
    t_total = _trapezoid_time_scalar(d, speed, accel)
    t_dec = t_total - t_acc
    out = np.where(
        t < t_acc,
        0.5 * accel * t * t,
        np.where(
            t < t_dec,
            0.5 * accel * t_acc**2 + v * (t - t_acc),
            d - 0.5 * accel * np.clip(t_total - t, 0.0, None) ** 2,
        ),
    )
    return np.clip(np.where(t <= 0, 0.0, out), 0.0, d)


@dataclass(frozen=True)
class RigPoses:
    """Where the devices are, in the sample frame (metres; origin at the sample centre).

    Attributes
    ----------
    wi, wo
        Unit directions from the sample centre towards the light and the camera.
    light_position
        Light centre, ``light_radius_m * wi``.
    light_normal
        The light's emitting normal, pointing at the sample centre (``-wi``).
    camera_position
        Camera centre of projection, ``camera_radius_m * wo``.
    camera_rotation
        3x3 matrix whose columns are the camera axes expressed in the sample frame, in the
        OpenCV convention: x right, y down (image rows), z forward (optical axis, towards
        the sample centre).  A point ``p_cam`` in camera coordinates is
        ``camera_rotation @ p_cam + camera_position`` in the sample frame; the OpenCV
        extrinsics (sample -> camera) are ``R = camera_rotation.T``,
        ``t = -camera_rotation.T @ camera_position``.  Image "up" is world up.
    sample_to_world
        Stage orientation: sample-frame vectors -> world vectors (world +z up).
    """

    wi: Array
    wo: Array
    light_position: Array
    light_normal: Array
    camera_position: Array
    camera_rotation: Array
    sample_to_world: Array


class Kinematics:
    """Forward and inverse kinematics of a rig configuration.

    Parameters
    ----------
    config
        The rig (its ``geometry`` and the servos' limits and motion profiles).
    """

    def __init__(self, config: RigConfig) -> None:
        g = config.geometry
        if g.kind != "arms_tilt_spin":  # pragma: no cover - pydantic already restricts kind
            raise ConfigError(f"geometry.kind {g.kind!r} is not supported")
        self.config = config
        self.geometry = g
        x_s = normalize(g.rest_reference)
        z_s = normalize(g.rest_normal)
        self._B = np.stack([x_s, np.cross(z_s, x_s), z_s], axis=1)  # columns: sample axes
        self.nominal = is_nominal(config)
        # Constant factors of the as-built stage transform (rig.asbuilt.stage_transform).
        k = normalize(np.asarray(g.tilt_axis, float))
        self._K_true = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
        self._B_true = asbuilt.rest_orientation(g)
        hx, hy = np.radians(g.holder_tilt_deg)
        self._H = asbuilt.elementary_rotation(1, hy) @ asbuilt.elementary_rotation(0, hx)
        self._o = np.asarray(g.holder_offset_m, float)
        self._t = np.asarray(g.stage_offset_m, float)
        # The closed form works on the nominal part: an as-built tilt axis made horizontal.
        self._k = normalize(np.array([g.tilt_axis[0], g.tilt_axis[1], 0.0]))
        # Up seen from the rest stage: v(t) = p cos t - q sin t with p = B^T z, q = B^T (k x z).
        self._p = self._B.T @ _Z
        self._q = self._B.T @ np.cross(self._k, _Z)
        self._tilt_amp = math.hypot(self._p[2], self._q[2])
        if self._tilt_amp < 1e-9:
            raise ConfigError(
                "geometry: tilting about tilt_axis never changes the stage's inclination"
            )
        self._tilt_phase = math.atan2(-self._q[2], self._p[2])
        self._eL = math.radians(g.light_elevation_deg)
        self._eC = math.radians(g.camera_elevation_deg)
        self.limits = {s.joint: s.limits_rad for s in config.servos}
        self._servo = {s.joint: s for s in config.servos}
        self._profile = {}
        for s in config.servos:
            model = MODELS.get(s.model)
            if model is None:
                raise ConfigError(
                    f"servo {s.id}: unknown model {s.model!r}; known: {sorted(MODELS)}"
                )
            speed = math.radians(s.velocity_deg_s) * s.gear_ratio
            accel = math.radians(s.acceleration_deg_s2) * s.gear_ratio
            self._profile[s.joint] = profile_pulses(
                velocity_register(speed), acceleration_register(accel), model
            )
        body = math.asin(min(1.0, g.camera_body_radius_m / g.camera_radius_m)) + math.asin(
            min(1.0, g.light_body_radius_m / g.light_radius_m)
        )
        self.min_separation = max(math.radians(g.min_separation_deg), body)
        self.arm_clearance = math.radians(g.arm_clearance_deg)
        self.max_theta = math.radians(g.max_theta_deg)

    # ------------------------------------------------------------------ forward
    def sample_to_world(self, tilt: ArrayLike, spin: ArrayLike) -> Array:
        """Stage rotation (sample -> world), shape (..., 3, 3), for joint angles (rad).

        ``A(tilt) @ B @ Rz(spin)`` on a nominal rig; on an as-built one ``M`` of
        :func:`gonio.rig.asbuilt.stage_transform` at the given (true) joint angles.
        """
        if not self.nominal:
            return asbuilt.stage_transform(self.geometry, tilt, spin)[0]
        return self._closed_M(tilt, spin)

    def _closed_M(self, tilt: ArrayLike, spin: ArrayLike) -> Array:
        return rotation_about(self._k, tilt) @ self._B @ rotation_about(_Z, spin)

    @staticmethod
    def _device(azimuth: ArrayLike, elevation: float) -> Array:
        a = np.asarray(azimuth, dtype=np.float64)
        ce = math.cos(elevation)
        return np.stack(
            np.broadcast_arrays(ce * np.cos(a), ce * np.sin(a), math.sin(elevation) + 0 * a), -1
        )

    def forward(
        self, joints: Joints, approach: Mapping[str, ArrayLike] | None = None
    ) -> tuple[Array, Array]:
        """Light and camera directions in the sample frame.

        Parameters
        ----------
        joints
            Joint name -> angle from the encoders (rad); floats or broadcastable arrays.
        approach
            Joint name -> sign of its last move (+1, -1, 0 unknown; None: unknown).  Only
            an as-built rig's backlash depends on it.

        Returns
        -------
        wi, wo : ndarray, shape (..., 3)
            Unit vectors from the sample centre towards the light and the camera.
        """
        self._require(joints)
        if not self.nominal:
            return self._asbuilt_directions(joints, approach)
        M = self._closed_M(joints["stage_tilt"], joints["stage_spin"])
        l = self._device(joints["light_azimuth"], self._eL)
        c = self._device(joints["camera_azimuth"], self._eC)
        Mt = np.swapaxes(M, -1, -2)
        return np.einsum("...ij,...j->...i", Mt, l), np.einsum("...ij,...j->...i", Mt, c)

    def _asbuilt_directions(
        self, joints: Mapping[str, ArrayLike], approach: Mapping[str, ArrayLike] | None
    ) -> tuple[Array, Array]:
        # rig_poses' directions, with the constant factors of the stage transform made
        # once (the refinement calls this in its loop); tests hold it to rig_poses.
        g = self.geometry
        q = asbuilt.true_joints(self.config, joints, approach)
        tilt, spin = np.asarray(q["stage_tilt"], float), np.asarray(q["stage_spin"], float)
        st, ct = np.sin(tilt)[..., None, None], np.cos(tilt)[..., None, None]
        A = np.eye(3) + st * self._K_true + (1.0 - ct) * (self._K_true @ self._K_true)
        ss, cs = np.sin(spin), np.cos(spin)
        zero, one = np.zeros_like(ss), np.ones_like(ss)
        S = np.stack(
            [
                np.stack([cs, -ss, zero], -1),
                np.stack([ss, cs, zero], -1),
                np.stack([zero, zero, one], -1),
            ],
            -2,
        )
        ABS = A @ self._B_true @ S
        M = ABS @ self._H
        T = ABS @ self._o + self._t
        P_L = self._device(q["light_azimuth"], self._eL) * g.light_radius_m
        P_C = self._device(q["camera_azimuth"], self._eC) * g.camera_radius_m
        Mt = np.swapaxes(M, -1, -2)
        wi = normalize(np.einsum("...ij,...j->...i", Mt, P_L - T))
        wo = normalize(np.einsum("...ij,...j->...i", Mt, P_C - T))
        return wi, wo

    def poses(self, joints: Joints, approach: Mapping[str, int] | None = None) -> RigPoses:
        """Positions and orientations of light and camera in the sample frame (metres).

        See :class:`RigPoses` for the conventions (camera axes: OpenCV, x right, y down,
        z forward towards the sample centre).  ``approach``: as :meth:`forward`.
        """
        self._require(joints)
        if not self.nominal:
            rp = asbuilt.rig_poses(self.config, {k: float(v) for k, v in joints.items()}, approach)
            return RigPoses(
                wi=rp.wi,
                wo=rp.wo,
                light_position=rp.light_position,
                light_normal=rp.light_normal,
                camera_position=rp.camera_position,
                camera_rotation=rp.camera_rotation,
                sample_to_world=rp.sample_to_world,
            )
        M = self._closed_M(float(joints["stage_tilt"]), float(joints["stage_spin"]))
        wi, wo = self.forward({k: float(v) for k, v in joints.items()})
        g = self.geometry
        # Looking at the sample centre with world up (in the sample frame) as image up.
        camera_rotation = look_along_rotation(-wo, up=M.T @ _Z).T
        return RigPoses(
            wi=wi,
            wo=wo,
            light_position=g.light_radius_m * wi,
            light_normal=-wi,
            camera_position=g.camera_radius_m * wo,
            camera_rotation=camera_rotation,
            sample_to_world=M,
        )

    # ------------------------------------------------------------------ motion
    def move_time(self, joints_from: Joints, joints_to: Joints) -> float:
        """Time (s) the servos need to move between two poses, each on its trapezoid profile.

        Uses the profile velocity and acceleration register values the controller writes
        (so the quantisation matches the servos), and the goal positions rounded to
        pulses.  Joints missing from either mapping do not move.
        """
        t = 0.0
        for j, (v, a) in self._profile.items():
            if j in joints_from and j in joints_to:
                s = self._servo[j]
                d = abs(
                    round(s.pulses(float(joints_to[j]))) - round(s.pulses(float(joints_from[j])))
                )
                t = max(t, _trapezoid_time_scalar(d, v, a))
        return t

    def joint_trajectory(
        self, joints_from: Joints, joints_to: Joints, n: int = 65
    ) -> dict[str, Array]:
        """Joint angles (rad) at ``n`` instants of a move, every servo on its own profile."""
        total = self.move_time(joints_from, joints_to)
        ts = np.linspace(0.0, total, n)
        out = {}
        for j in JOINT_NAMES:
            s = self._servo[j]
            p0, p1 = s.pulses(float(joints_from[j])), s.pulses(float(joints_to[j]))
            v, a = self._profile[j]
            covered = trapezoid_position(abs(p1 - p0), v, a, ts)
            out[j] = s.joint_rad(p0 + np.copysign(covered, p1 - p0))
        return out

    # ------------------------------------------------------------------ checks
    def _pose_reason(self, q: Joints, wi: Array, wo: Array) -> PoseRefused | None:
        for j, (lo, hi) in self.limits.items():
            if not lo - 1e-12 <= q[j] <= hi + 1e-12:
                return PoseRefused(
                    RefusalReason.JOINT_LIMIT,
                    f"{j} would need {math.degrees(q[j]):.3f} deg, outside its limits "
                    f"[{math.degrees(lo):.1f}, {math.degrees(hi):.1f}] deg",
                )
        sep = float(angle_between(wi, wo))
        if sep < self.min_separation:
            return PoseRefused(
                RefusalReason.SHADOWING,
                f"light and camera only {math.degrees(sep):.2f} deg apart seen from the sample "
                f"(minimum {math.degrees(self.min_separation):.2f} deg): the camera would shadow "
                "the light (or the light block the camera)",
            )
        gap = abs(float(_wrap(q["light_azimuth"] - q["camera_azimuth"])))
        if gap < self.arm_clearance:
            return PoseRefused(
                RefusalReason.ARM_CLEARANCE,
                f"light and camera arms {math.degrees(gap):.2f} deg apart in azimuth, below the "
                f"arm clearance {math.degrees(self.arm_clearance):.2f} deg (arms would collide)",
            )
        return None

    def path_refusal(self, q0: Joints, q1: Joints) -> PoseRefused | None:
        """Why the move from joints ``q0`` to ``q1`` (rad) is not allowed, or None.

        With arms that cannot cross, both arms follow their servos' trapezoid profiles
        and must keep their order and the arm clearance all the way
        (``RefusalReason.PATH``).
        """
        self._require(q0)
        self._require(q1)
        if self.geometry.arms_can_cross:
            return None
        path = self.joint_trajectory(q0, q1)
        d = path["camera_azimuth"] - path["light_azimuth"]
        if np.any(np.sign(d) != np.sign(d[0])) or np.min(np.abs(d)) < self.arm_clearance - 1e-12:
            return PoseRefused(
                RefusalReason.PATH,
                "the move would make the light and camera arms pass or touch each other "
                f"(azimuth gap down to {math.degrees(float(np.min(np.abs(d)))):.2f} deg)",
            )
        return None

    def _direction_reason(self, wi: Array, wo: Array) -> PoseRefused | None:
        for name, w in (("wi", wi), ("wo", wo)):
            if not np.all(np.isfinite(w)) or np.linalg.norm(w) < 1e-9:
                return PoseRefused(
                    RefusalReason.INVALID_DIRECTION,
                    f"{name} = {w.tolist()} is not a finite non-zero direction",
                )
        ti, to = float(np.arccos(np.clip(wi[2], -1, 1))), float(np.arccos(np.clip(wo[2], -1, 1)))
        for name, th in (("theta_i", ti), ("theta_o", to)):
            if th > self.max_theta:
                return PoseRefused(
                    RefusalReason.BEYOND_RIM,
                    f"{name} = {math.degrees(th):.2f} deg beyond "
                    f"{math.degrees(self.max_theta):.1f} deg: "
                    "the sample holder's rim blocks that direction",
                )
        return None

    def direction_refusal(self, wi: ArrayLike, wo: ArrayLike) -> PoseRefused | None:
        """Why the directions themselves cannot be asked for (not finite, zero, beyond the
        holder's rim), or None; whatever the joints."""
        wi = np.asarray(wi, dtype=np.float64).reshape(3)
        wo = np.asarray(wo, dtype=np.float64).reshape(3)
        r = self._direction_reason(wi, wo)
        if r is not None:
            return r
        return self._direction_reason(wi / np.linalg.norm(wi), wo / np.linalg.norm(wo))

    def _candidates(
        self, wi: Array, wo: Array
    ) -> tuple[list[dict[str, float]], PoseRefused | None]:
        """All joint solutions within the limits' turn counts (not yet checked)."""
        sL, sC = math.sin(self._eL), math.sin(self._eC)
        c = float(wi @ wo)
        cross = np.cross(wi, wo)
        ncross = float(np.linalg.norm(cross))
        if ncross < 1e-9:
            return [], PoseRefused(
                RefusalReason.NO_SOLUTION,
                "wi and wo are parallel: light and camera would have to be in the same place",
            )
        det = 1.0 - c * c
        alpha, beta = (sL - c * sC) / det, (sC - c * sL) / det
        r2 = alpha * sL + beta * sC
        if r2 > 1.0 + 1e-12:
            return [], PoseRefused(
                RefusalReason.NO_SOLUTION,
                "no stage orientation puts both directions at the arms' elevations",
            )
        gamma = math.sqrt(max(0.0, 1.0 - r2)) / ncross
        out = []
        reason = None
        for sign in (1.0, -1.0):
            u = alpha * wi + beta * wo + sign * gamma * cross
            u = u / np.linalg.norm(u)
            ratio = u[2] / self._tilt_amp
            if abs(ratio) > 1.0 + 1e-12:
                reason = PoseRefused(
                    RefusalReason.TILT_RANGE, "the stage cannot tilt far enough for this pair"
                )
                continue
            half = math.acos(max(-1.0, min(1.0, ratio)))
            for t in {self._tilt_phase + half, self._tilt_phase - half}:
                v = self._p * math.cos(t) - self._q * math.sin(t)
                s = math.atan2(v[1], v[0]) - math.atan2(u[1], u[0])
                M = self._closed_M(t, s)
                l, cam = M @ wi, M @ wo
                aL, aC = math.atan2(l[1], l[0]), math.atan2(cam[1], cam[0])
                base = {"light_azimuth": aL, "camera_azimuth": aC, "stage_tilt": t, "stage_spin": s}
                options = []
                for j in JOINT_NAMES:
                    lo, hi = self.limits[j]
                    k0 = math.ceil((lo - base[j]) / (2 * math.pi) - 1e-9)
                    k1 = math.floor((hi - base[j]) / (2 * math.pi) + 1e-9)
                    vals = [base[j] + 2 * math.pi * k for k in range(k0, k1 + 1)]
                    if not vals:  # keep the nearest so the reason names the joint
                        vals = [
                            base[j] + 2 * math.pi * round(((lo + hi) / 2 - base[j]) / (2 * math.pi))
                        ]
                    options.append(vals)
                for combo in itertools.product(*options):
                    out.append(dict(zip(JOINT_NAMES, combo, strict=True)))
        return out, reason

    def _move_signs(self, Q: Array, ref: Joints, approach: Mapping[str, int] | None) -> Array:
        """Approach signs (n, 4) of moves from ``ref`` to each row of ``Q`` (rad, (n, 4)):
        :func:`approach_of_move`, with an unknown sign of a joint that does not move
        counted as +1 (the rig takes its backlash up from below)."""
        out = np.empty_like(Q)
        for k, j in enumerate(JOINT_NAMES):
            s = self._servo[j]
            zero = s.zero_deg * 4096.0 / 360.0
            scale = s.direction * s.gear_ratio * 4096.0 / (2 * math.pi)
            d = np.round(zero + scale * Q[:, k]) - round(s.pulses(float(ref[j])))
            keep = int((approach or {}).get(j, 0)) or 1
            out[:, k] = side_after(
                take_up_servo(s, self.config), d, keep, self.config.motion.position_tolerance_pulses
            )
        return out

    def _residual(self, Q: Array, signs: Array, target: Array) -> Array:
        joints = {j: Q[..., k] for k, j in enumerate(JOINT_NAMES)}
        appr = {j: signs[..., k] for k, j in enumerate(JOINT_NAMES)}
        wi, wo = self._asbuilt_directions(joints, appr)
        return np.concatenate([wi, wo], axis=-1) - target

    def refine(
        self,
        wi: ArrayLike,
        wo: ArrayLike,
        start: Joints | list[Joints],
        current: Joints | None = None,
        approach: Mapping[str, int] | None = None,
    ) -> list[dict[str, float] | None]:
        """Gauss-Newton steps on the as-built model from each of ``start`` (rad) until
        (wi, wo) are met to 1e-9 rad; None for a start that does not get there.

        The approach signs are those of the move from ``current`` (home when None)
        with ``approach`` kept by joints that do not move (see the module docstring).
        """
        starts = [start] if isinstance(start, Mapping) else list(start)
        if not starts:
            return []
        wi = normalize(np.asarray(wi, dtype=np.float64).reshape(3))
        wo = normalize(np.asarray(wo, dtype=np.float64).reshape(3))
        target = np.concatenate([wi, wo])
        ref = dict(current) if current is not None else self.config.home_rad
        Q = np.array([[float(q[j]) for j in JOINT_NAMES] for q in starts])
        steps = np.zeros((9, 4))
        for k in range(4):
            steps[1 + 2 * k, k], steps[2 + 2 * k, k] = _JAC_STEP, -_JAC_STEP
        err = np.full(len(Q), np.inf)
        for _ in range(_REFINE_STEPS):
            signs = self._move_signs(Q, ref, approach)
            F = self._residual(Q[:, None, :] + steps, signs[:, None, :], target)  # (n, 9, 6)
            err = np.max(np.abs(F[:, 0]), axis=-1)
            if np.all(err < 0.1 * _REFINE_TOL):
                break
            J = (F[:, 1::2] - F[:, 2::2]) / (2 * _JAC_STEP)  # (n, 4, 6): d residual / d q_k
            for n in range(len(Q)):
                if np.isfinite(err[n]) and err[n] >= 0.1 * _REFINE_TOL:
                    dq = np.linalg.lstsq(J[n].T, -F[n, 0], rcond=None)[0]
                    Q[n] += np.clip(dq, -0.5, 0.5)  # a far start must not jump branches
        signs = self._move_signs(Q, ref, approach)
        err = np.max(np.abs(self._residual(Q, signs, target)), axis=-1)
        return [
            dict(zip(JOINT_NAMES, map(float, Q[n]), strict=True)) if err[n] < _REFINE_TOL else None
            for n in range(len(Q))
        ]

    def _solve(
        self,
        wi: ArrayLike,
        wo: ArrayLike,
        current: Joints | None,
        approach: Mapping[str, int] | None = None,
    ) -> tuple[dict | None, PoseRefused | None]:
        wi = np.asarray(wi, dtype=np.float64).reshape(3)
        wo = np.asarray(wo, dtype=np.float64).reshape(3)
        reason = self._direction_reason(wi, wo)
        if reason:
            return None, reason
        wi, wo = wi / np.linalg.norm(wi), wo / np.linalg.norm(wo)
        cands, reason = self._candidates(wi, wo)
        ref = dict(current) if current is not None else self.config.home_rad
        best, best_cost = None, math.inf
        reasons = [reason] if reason else []
        if not self.nominal and cands:
            # A joint the backlash alone would move may stay where it is (keeping its
            # side) or cross the backlash: refine from both, the shorter move wins.
            near = []
            for q in cands:
                snap = dict(q)
                for j in JOINT_NAMES:
                    sv = self._servo[j]
                    reach = math.radians(sv.backlash_deg) + 2 * math.pi / 4096 / sv.gear_ratio
                    if abs(q[j] - ref[j]) <= reach:
                        snap[j] = float(ref[j])
                if snap != q:
                    near.append(snap)
            refined = self.refine(wi, wo, cands + near, current, approach)
            if any(q is None for q in refined):
                reasons.append(
                    PoseRefused(
                        RefusalReason.NO_SOLUTION,
                        "the as-built model has no solution near the nominal one",
                    )
                )
            cands = [q for q in refined if q is not None]
        for q in cands:
            r = self._pose_reason(q, wi, wo)
            if r is None and current is not None:
                r = self.path_refusal(ref, q)
            elif r is None and not self.geometry.arms_can_cross:
                # no current pose: keep the arms in the home pose's order
                d0 = ref["camera_azimuth"] - ref["light_azimuth"]
                if np.sign(q["camera_azimuth"] - q["light_azimuth"]) != np.sign(d0):
                    r = PoseRefused(
                        RefusalReason.PATH,
                        "the arms would have to pass each other (order differs from home)",
                    )
            if r is not None:
                reasons.append(r)
                continue
            cost = self.move_time(ref, q) + 1e-6 * sum(abs(q[j] - ref[j]) for j in JOINT_NAMES)
            if cost < best_cost:
                best, best_cost = q, cost
        if best is None:
            # The most specific reason: prefer limit / shadow reasons over the path ones.
            reasons.sort(key=lambda r: r.reason is RefusalReason.PATH)
            if not reasons:
                return None, PoseRefused(RefusalReason.NO_SOLUTION, "no solution")
            return None, reasons[0]
        return best, None

    def inverse(
        self,
        wi: ArrayLike,
        wo: ArrayLike,
        current: Joints | None = None,
        approach: Mapping[str, int] | None = None,
    ) -> dict[str, float]:
        """Joint angles (rad) that put the light along ``wi`` and the camera along ``wo``.

        Parameters
        ----------
        wi, wo
            Directions in the sample frame (shape (3,), need not be normalised).
        current
            Present joint angles (rad); the solution with the shortest move from there
            (from the home pose if None) is chosen among the reachable, collision-free ones.
        approach
            The joints' present approach signs (+1, -1, 0 unknown): on an as-built rig,
            a joint the move leaves in place keeps its sign (unknown counts as +1).

        Raises
        ------
        PoseRefused
            If no solution is reachable; ``reason`` says which rule and the message why
            (limits, camera shadow, arm collision, holder rim, parallel directions).
        """
        q, refusal = self._solve(wi, wo, current, approach)
        if q is None:
            raise PoseRefused(
                refusal.reason,
                f"cannot reach wi={np.round(np.asarray(wi, float), 6).tolist()}, "
                f"wo={np.round(np.asarray(wo, float), 6).tolist()}: {refusal}",
            )
        return q

    def refusal(
        self,
        wi: ArrayLike,
        wo: ArrayLike,
        current: Joints | None = None,
        approach: Mapping[str, int] | None = None,
    ) -> PoseRefused | None:
        """Why ``(wi, wo)`` cannot be reached, or None when it can.

        Parameters
        ----------
        wi, wo
            Directions in the sample frame (shape (3,)).
        current
            Present joint angles (rad): the path from there is checked too.
        approach
            Present approach signs (as :meth:`inverse`).

        Returns
        -------
        PoseRefused or None
            The refusal (not raised): ``reason`` is the rule, ``str()`` the sentence.
        """
        return self._solve(wi, wo, current, approach)[1]

    def check(self, wi: ArrayLike, wo: ArrayLike, current: Joints | None = None) -> str | None:
        """Why ``(wi, wo)`` cannot be reached (a sentence), or None when it can."""
        r = self.refusal(wi, wo, current)
        return None if r is None else str(r)

    def joints_refusal(
        self, joints: Joints, approach: Mapping[str, int] | None = None
    ) -> PoseRefused | None:
        """Why a joint pose (rad) is not allowed (rim, limits, shadow, clearance), or None.

        ``approach``: the joints' approach signs there (as :meth:`forward`)."""
        self._require(joints)
        wi, wo = self.forward(joints, approach)
        return self._direction_reason(wi, wo) or self._pose_reason(joints, wi, wo)

    def check_joints(self, joints: Joints) -> str | None:
        """Why a joint pose is not allowed (limits, shadow, clearance), or None."""
        r = self.joints_refusal(joints)
        return None if r is None else str(r)

    @staticmethod
    def _require(joints: Joints) -> None:
        missing = [j for j in JOINT_NAMES if j not in joints]
        if missing:
            raise RigError(f"joint angles missing for {missing}; expected all of {JOINT_NAMES}")
