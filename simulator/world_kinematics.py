"""Where the as-built rig really puts the light, the camera and the sample.

The physics of :mod:`gonio.simulator.world`, from the servos' true state (encoder pulses
and the direction of each servo's last move) to poses in the sample frame.  Written
independently of the controller's model (:mod:`gonio.rig.asbuilt`: the simulator may not
import it); both implement the definitions in DEVELOPING.md ("The as-built world"), and
tests compare them to 1e-12.

Definitions (world frame: origin on the arms' axis at the stage's height, +z up)::

    q_r = nominal encoder reading + offset               (rad)
    q   = q_r - s * backlash / 2 + a cos q_r + b sin q_r  (s: sign of the last move)
    P_L = r_L d(q_light, e_L),  P_C = r_C d(q_camera, e_C),  d(a, e) = (ce ca, ce sa, se)
    R_cw = R0(P_C) @ Rz(m_z) @ Ry(m_y) @ Rx(m_x)          (R0: looking at the origin, +z up)
    M = rot(k, q_tilt) @ B @ Rz(q_spin) @ Ry(h_y) @ Rx(h_x)
    T = rot(k, q_tilt) @ B @ Rz(q_spin) @ o + (t_x, t_y, 0)

with ``k = rot(normalize(k0 x z), pitch) k0`` and ``B`` from ``rot(u, yaw) n0``,
``rot(u, yaw) r0`` (``u = normalize(k0 x n0)``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict

from gonio.simulator.world import JOINTS, World

__all__ = [
    "NominalRig",
    "TruePoses",
    "approach_from_servos",
    "joint_truth",
    "poses_from_joints",
    "readings_from_pulses",
    "true_poses",
]

Array = NDArray[np.float64]
_PULSES_PER_TURN = 4096.0
_ZHAT = np.array([0.0, 0.0, 1.0])


class _Loose(BaseModel):
    model_config = ConfigDict(extra="ignore", frozen=True)


class _Servo(_Loose):
    id: int
    joint: str
    zero_deg: float = 180.0
    direction: Literal[1, -1] = 1
    gear_ratio: float = 1.0


class _Geometry(_Loose):
    light_radius_m: float = 0.50
    camera_radius_m: float = 0.40
    light_elevation_deg: float = 0.0
    camera_elevation_deg: float = 0.0
    tilt_axis: tuple[float, float, float] = (0.0, -1.0, 0.0)
    rest_normal: tuple[float, float, float] = (1.0, 0.0, 0.0)
    rest_reference: tuple[float, float, float] = (0.0, 0.0, 1.0)


class NominalRig(_Loose):
    """The few fields of a nominal rig TOML the world needs (servos, geometry)."""

    servos: tuple[_Servo, ...]
    geometry: _Geometry = _Geometry()

    @classmethod
    def of(cls, rig_doc: Mapping[str, Any] | NominalRig) -> NominalRig:
        """From a rig TOML dict (or a ready one)."""
        return rig_doc if isinstance(rig_doc, NominalRig) else cls.model_validate(dict(rig_doc))

    def servo(self, joint: str) -> _Servo:
        for s in self.servos:
            if s.joint == joint:
                return s
        raise KeyError(f"no servo drives joint {joint!r}")


@dataclass(frozen=True)
class TruePoses:
    """Poses of the as-built rig in the sample frame (m), like the controller's poses.

    ``camera_rotation``: camera -> sample, columns the OpenCV camera axes.
    ``sample_to_world`` (M) and ``sample_origin`` (T): a sample point x is at M x + T.
    ``joints``: the true joint angles (rad).
    """

    wi: Array
    wo: Array
    light_position: Array
    light_normal: Array
    camera_position: Array
    camera_rotation: Array
    sample_to_world: Array
    sample_origin: Array
    joints: Mapping[str, float]
    #: The light body's "up" in its face plane (sample frame): the light is fixed to its
    #: arm, so its face (and the face's non-uniformity) turns with the arm, not with the
    #: stage.  ``up = e_az x n`` with ``e_az`` the arm's azimuth tangent and ``n`` the
    #: emitting normal.
    light_up: Array | None = None


def _unit(v: Array) -> Array:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def _cross(a: Array, b: Array) -> Array:
    # np.cross costs ~20 us a call; the views call this thousands of times.
    return np.array(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def _rot(axis: Array, angle: float) -> Array:
    """Right-handed rotation by ``angle`` (rad) about ``axis`` (counter-clockwise seen
    from its tip): ``cos I + sin [k]x + (1 - cos) k k^T``."""
    kx, ky, kz = _unit(axis)
    c, s = math.cos(angle), math.sin(angle)
    v = 1.0 - c
    return np.array(
        [
            [c + kx * kx * v, kx * ky * v - kz * s, kx * kz * v + ky * s],
            [ky * kx * v + kz * s, c + ky * ky * v, ky * kz * v - kx * s],
            [kz * kx * v - ky * s, kz * ky * v + kx * s, c + kz * kz * v],
        ]
    )


def _axis_rot(i: int, angle: float) -> Array:
    e = np.zeros(3)
    e[i] = 1.0
    return _rot(e, angle)


def joint_truth(
    world: World, rig: NominalRig, readings: Mapping[str, float], approach: Mapping[str, int]
) -> dict[str, float]:
    """True joint angles (rad) from the nominal encoder readings (rad, through the
    nominal zero) and the sign of each joint's last move (+1 angle increased, -1, 0)."""
    p = world.rig
    out = {}
    for j in JOINTS:
        q_r = float(readings[j]) + math.radians(p[f"{j}.offset"])
        q = q_r - int(approach.get(j, 0)) * math.radians(p[f"{j}.backlash"]) / 2.0
        if j == "stage_tilt":
            a = math.radians(p["stage_tilt.compliance_a"])
            b = math.radians(p["stage_tilt.compliance_b"])
            q += a * math.cos(q_r) + b * math.sin(q_r)
        out[j] = q
    return out


def _stage_axes(world: World, rig: NominalRig) -> tuple[Array, Array]:
    """The true tilt axis ``k`` and rest orientation ``B`` (columns: sample x, y, z)."""
    g, p = rig.geometry, world.rig
    k0, n0, r0 = _unit(g.tilt_axis), _unit(g.rest_normal), _unit(g.rest_reference)
    k = _rot(_cross(k0, _ZHAT), math.radians(p["tilt_axis_pitch"])) @ k0
    turn = _rot(_cross(k0, n0), math.radians(p["spin_axis_yaw"]))
    z_s, x_s = _unit(turn @ n0), _unit(turn @ r0)
    return _unit(k), np.column_stack([x_s, _cross(z_s, x_s), z_s])


def _arm(radius: float, azimuth: float, elevation_deg: float) -> Array:
    e = math.radians(elevation_deg)
    return radius * np.array(
        [math.cos(e) * math.cos(azimuth), math.cos(e) * math.sin(azimuth), math.sin(e)]
    )


def _look_at_origin(position: Array) -> Array:
    """Camera -> world rotation (columns x right, y down, z forward) of a camera at
    ``position`` looking at the origin with world +z as image up."""
    f = _unit(-position)
    x = _unit(_cross(f, _ZHAT))
    y = _cross(f, x)
    return np.column_stack([x, y, f])


def poses_from_joints(world: World, rig_doc: Any, q: Mapping[str, float]) -> TruePoses:
    """Poses of the as-built rig at the TRUE joint angles ``q`` (rad)."""
    rig = NominalRig.of(rig_doc)
    t = world.truth_parameters(_geometry_doc(rig))
    p = world.rig
    k, B = _stage_axes(world, rig)
    ABS = _rot(k, q["stage_tilt"]) @ B @ _axis_rot(2, q["stage_spin"])
    H = _axis_rot(1, math.radians(p["holder_tilt_y"])) @ _axis_rot(
        0, math.radians(p["holder_tilt_x"])
    )
    M = ABS @ H
    o = np.array([p["holder_offset_x"], p["holder_offset_y"], p["holder_offset_z"]])
    T = ABS @ o + np.array([p["stage_offset_x"], p["stage_offset_y"], 0.0])
    P_L = _arm(t["light_radius"], q["light_azimuth"], t["light_elevation"])
    P_C = _arm(t["camera_radius"], q["camera_azimuth"], t["camera_elevation"])
    mount = (
        _axis_rot(2, math.radians(p["camera_mount_z"]))
        @ _axis_rot(1, math.radians(p["camera_mount_y"]))
        @ _axis_rot(0, math.radians(p["camera_mount_x"]))
    )
    R_cw = _look_at_origin(P_C) @ mount
    lp, cp = M.T @ (P_L - T), M.T @ (P_C - T)
    n_L = _unit(-P_L)
    e_az = np.array([-math.sin(q["light_azimuth"]), math.cos(q["light_azimuth"]), 0.0])
    return TruePoses(
        wi=_unit(lp),
        wo=_unit(cp),
        light_position=lp,
        light_normal=M.T @ n_L,
        camera_position=cp,
        camera_rotation=M.T @ R_cw,
        sample_to_world=M,
        sample_origin=T,
        joints=dict(q),
        light_up=M.T @ _cross(e_az, n_L),
    )


def _geometry_doc(rig: NominalRig) -> dict[str, Any]:
    return {"geometry": rig.geometry.model_dump()}


def readings_from_pulses(rig: NominalRig, pulses: Mapping[int, float]) -> dict[str, float]:
    """Joint readings (rad) through the NOMINAL zero: what the controller computes from
    the encoders (servo id -> pulses)."""
    out = {}
    for s in rig.servos:
        zero = s.zero_deg * _PULSES_PER_TURN / 360.0
        out[s.joint] = (
            s.direction * (float(pulses[s.id]) - zero) * (2 * math.pi / _PULSES_PER_TURN)
        ) / s.gear_ratio
    return out


def approach_from_servos(rig: NominalRig, directions: Mapping[int, int]) -> dict[str, int]:
    """Sign of each joint's last move from the sign of each servo's last move (pulses)."""
    return {s.joint: int(np.sign(directions.get(s.id, 0))) * s.direction for s in rig.servos}


def true_poses(
    world: World, rig_doc: Any, servo_states: Mapping[int, tuple[float, int]]
) -> TruePoses:
    """Poses of the as-built rig from the servos' true state.

    Parameters
    ----------
    world
        The as-built world.
    rig_doc
        The NOMINAL rig configuration as a TOML dict (servo ids, joints, zero_deg,
        direction, gear_ratio; geometry).
    servo_states
        Servo id -> (Present Position in pulses, sign of its last move in pulses: +1, -1,
        0 never moved), e.g. :meth:`gonio.simulator.virtual_bus.ServoBus.servo_states`.

    Returns
    -------
    TruePoses
        In the sample frame, metres.
    """
    rig = NominalRig.of(rig_doc)
    readings = readings_from_pulses(rig, {i: st[0] for i, st in servo_states.items()})
    approach = approach_from_servos(rig, {i: st[1] for i, st in servo_states.items()})
    return poses_from_joints(world, rig, joint_truth(world, rig, readings, approach))
