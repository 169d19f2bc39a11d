"""The controller's model of the rig as built: joint readings -> light, camera and sample.

A nominal rig configuration has every as-built term at zero, and this model then gives
exactly the poses of the nominal geometry (:class:`gonio.rig.kinematics.Kinematics`
documents those).  ``gonio calibrate rig`` measures the terms and writes them into a
calibrated configuration; the kinematics, the session and the reduction then use them.
The simulator's as-built world (``gonio.simulator.world``) implements the same physical
definitions independently, so tests of one check the other.

Definitions (world frame: origin on the arms' vertical axis, +z up; radians inside)
-----------------------------------------------------------------------------------
Joint angles.  ``q_r`` is the angle the encoder gives through the servo's ``zero_deg``,
``direction`` and ``gear_ratio`` (a calibrated ``zero_deg`` carries the zero offset).
``s`` is the sign of the joint's last move (+1 when its angle increased, -1 when it
decreased, 0 unknown).  The joint's true angle is::

    q = q_r - s * backlash / 2 + a cos(q_r) + b sin(q_r)        (a, b) = compliance

(the joint lags the encoder by half the backlash on the side it came from, and bends
under gravity).

Arms.  ``d(a, e) = (cos e cos a, cos e sin a, sin e)``; the light's centre is
``P_L = light_radius * d(q_light, light_elevation)`` and the camera's centre
``P_C = camera_radius * d(q_camera, camera_elevation)``.  The light aims at the origin
(its emitting normal is ``-P_L / |P_L|``).  The camera's axes (OpenCV: x right, y down,
z forward) are those of a camera at ``P_C`` looking at the origin with world +z as image
up, ``R0`` (columns: the axes in the world), turned on its mount: camera-to-world
``R_cw = R0 @ Rz(m_z) @ Ry(m_y) @ Rx(m_x)``, ``m = camera_mount``.

Stage.  ``k = tilt_axis`` (unit), ``B`` the rest orientation (columns: sample x, y, z at
rest, from ``rest_reference`` and ``rest_normal``), ``A = rot(k, q_tilt)``,
``S = rot(z, q_spin)``, ``H = Ry(h_y) @ Rx(h_x)`` (``holder_tilt``).  A sample-frame point
``x`` is at ``M x + T`` in the world, with::

    M = A @ B @ S @ H                T = A @ B @ S @ o + t

``o = holder_offset`` (the sample centre in the spin plate's frame) and ``t =
stage_offset`` (the stage's rotation centre from the arms' axis).

In the sample frame: ``light_position = M^T (P_L - T)``, ``camera_position = M^T (P_C - T)``,
``camera_rotation = M^T R_cw``, ``wi``/``wo`` their unit directions from the sample
centre, ``light_normal = M^T (-P_L / |P_L|)``.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gonio.radiometry.frames import look_along_rotation, normalize, rotation_about
from gonio.rig.config import JOINT_NAMES, GeometryConfig, RigConfig

__all__ = [
    "AsBuiltPoses",
    "camera_to_world",
    "elementary_rotation",
    "rest_orientation",
    "rig_poses",
    "stage_transform",
    "true_joints",
]

Array = NDArray[np.float64]
_Z = np.array([0.0, 0.0, 1.0])


def elementary_rotation(axis: int, angle: ArrayLike) -> Array:
    """Rotation matrices about coordinate axis ``axis`` (0: x, 1: y, 2: z) by ``angle``
    (rad, any shape), shape ``angle.shape + (3, 3)``."""
    e = np.zeros(3)
    e[axis] = 1.0
    return rotation_about(e, np.asarray(angle, dtype=np.float64))


def rest_orientation(geometry: GeometryConfig) -> Array:
    """``B``: columns are the sample's x, y, z axes in the world at tilt = spin = 0."""
    x_s = normalize(np.asarray(geometry.rest_reference, float))
    z_s = normalize(np.asarray(geometry.rest_normal, float))
    return np.stack([x_s, np.cross(z_s, x_s), z_s], axis=1)


def true_joints(
    config: RigConfig,
    joints: Mapping[str, ArrayLike],
    approach: Mapping[str, ArrayLike] | None = None,
) -> dict[str, Array]:
    """The joints' true angles (rad) from the encoder readings (rad) and the sign of
    each joint's last move (+1, -1, 0 unknown; None: all unknown)."""
    out = {}
    for s in config.servos:
        q = np.asarray(joints[s.joint], dtype=np.float64)
        sign = 0.0 if approach is None else np.asarray(approach.get(s.joint, 0), float)
        a, b = np.radians(s.compliance_deg)
        out[s.joint] = q - sign * np.radians(s.backlash_deg) / 2.0 + a * np.cos(q) + b * np.sin(q)
    return out


def stage_transform(
    geometry: GeometryConfig, tilt: ArrayLike, spin: ArrayLike
) -> tuple[Array, Array]:
    """``(M, T)``: sample-frame point ``x`` is at ``M @ x + T`` in the world (metres).

    Shapes ``(..., 3, 3)`` and ``(..., 3)`` for true joint angles ``tilt``, ``spin``
    (rad) of shape ``(...)``.
    """
    k = normalize(np.asarray(geometry.tilt_axis, float))
    A = rotation_about(k, np.asarray(tilt, float))
    ABS = A @ rest_orientation(geometry) @ rotation_about(_Z, np.asarray(spin, float))
    hx, hy = np.radians(geometry.holder_tilt_deg)
    H = elementary_rotation(1, hy) @ elementary_rotation(0, hx)
    o = np.asarray(geometry.holder_offset_m, float)
    T = np.einsum("...ij,j->...i", ABS, o) + np.asarray(geometry.stage_offset_m, float)
    return ABS @ H, T


def _device(radius: float, azimuth: Array, elevation_deg: float) -> Array:
    e = np.radians(elevation_deg)
    a = np.asarray(azimuth, float)
    return radius * np.stack(
        np.broadcast_arrays(np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e) + 0 * a), -1
    )


def camera_to_world(geometry: GeometryConfig, camera_position: Array) -> Array:
    """``R_cw`` (columns: the camera's x, y, z axes in the world) of a camera at
    ``camera_position`` (world, m) aimed at the origin and turned on its mount."""
    R0 = np.swapaxes(look_along_rotation(-normalize(camera_position), _Z), -1, -2)
    mx, my, mz = np.radians(geometry.camera_mount_deg)
    mount = elementary_rotation(2, mz) @ elementary_rotation(1, my) @ elementary_rotation(0, mx)
    return R0 @ mount


class AsBuiltPoses:
    """Poses in the sample frame (metres), arrays with the joints' leading shape.

    Attributes as :class:`gonio.rig.kinematics.RigPoses`: ``wi``, ``wo``,
    ``light_position``, ``light_normal``, ``camera_position``, ``camera_rotation``
    (camera-to-sample, OpenCV axes), ``sample_to_world`` (``M``), plus
    ``sample_origin`` (``T``, the sample centre in the world).
    """

    __slots__ = (
        "wi",
        "wo",
        "light_position",
        "light_normal",
        "camera_position",
        "camera_rotation",
        "sample_to_world",
        "sample_origin",
    )

    def __init__(self, **kw: Array) -> None:
        for k, v in kw.items():
            setattr(self, k, v)


def rig_poses(
    config: RigConfig,
    joints: Mapping[str, ArrayLike],
    approach: Mapping[str, ArrayLike] | None = None,
) -> AsBuiltPoses:
    """Light, camera and sample of the rig as built, in the sample frame.

    Parameters
    ----------
    config
        The rig configuration (nominal or calibrated).
    joints
        Joint name -> angle from the encoders (rad); floats or broadcastable arrays.
    approach
        Joint name -> sign of its last move (+1, -1, 0 unknown); None: unknown.

    Returns
    -------
    AsBuiltPoses
        See the module docstring for the definitions.
    """
    missing = [j for j in JOINT_NAMES if j not in joints]
    if missing:
        from gonio.errors import RigError

        raise RigError(f"joint angles missing for {missing}; expected all of {JOINT_NAMES}")
    g = config.geometry
    q = true_joints(config, joints, approach)
    M, T = stage_transform(g, q["stage_tilt"], q["stage_spin"])
    P_L = _device(g.light_radius_m, q["light_azimuth"], g.light_elevation_deg)
    P_C = _device(g.camera_radius_m, q["camera_azimuth"], g.camera_elevation_deg)
    Mt = np.swapaxes(M, -1, -2)

    def to_sample(v: Array) -> Array:
        return np.einsum("...ij,...j->...i", Mt, v)

    lp = to_sample(P_L - T)
    cp = to_sample(P_C - T)
    return AsBuiltPoses(
        wi=normalize(lp),
        wo=normalize(cp),
        light_position=lp,
        light_normal=to_sample(-normalize(P_L)),
        camera_position=cp,
        camera_rotation=Mt @ camera_to_world(g, P_C),
        sample_to_world=M,
        sample_origin=T,
    )
