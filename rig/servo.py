"""A servo in SI units: joint angle (rad), speed (rad/s), temperature (degC), current (A).

:class:`Servo` turns a :class:`ServoConfig` (gear ratio, direction, zero, limits) and the
control table into register values for the bus (any :class:`~gonio.rig.bus.BusTransport`),
and decodes the state
block the rig sync-reads every cycle (:func:`decode_state`).
"""

from __future__ import annotations

import math
import struct
from typing import NamedTuple

from gonio.errors import PoseRefused, RefusalReason, RigError
from gonio.rig import control_table as ct
from gonio.rig.bus import BusTransport
from gonio.rig.config import ServoConfig


class ServoState(NamedTuple):
    """One servo's state, decoded from the cyclic block (immutable; a named tuple
    because it is built for every servo on every cycle).

    Attributes
    ----------
    dxl_id, joint
        Bus ID and joint name.
    position
        Joint angle (rad).
    goal
        Joint angle the servo is heading to (rad).
    position_pulses, goal_pulses
        The raw counts.
    velocity
        Joint speed (rad/s).
    current
        Motor current (A).
    voltage
        Input voltage (V).
    temperature
        Internal temperature (degC).
    torque, moving
        Torque enabled; profile still running.
    in_position
        Moving Status bit 0.
    hardware_error
        Register 70 (0 when healthy).
    """

    dxl_id: int
    joint: str
    position: float
    goal: float
    position_pulses: int
    goal_pulses: int
    velocity: float
    current: float
    voltage: float
    temperature: float
    torque: bool
    moving: bool
    in_position: bool
    hardware_error: int

    @property
    def error_names(self) -> list[str]:
        """Names of the Hardware Error Status bits that are set."""
        return [n for bit, n in ct.HW_ERROR_NAMES.items() if self.hardware_error & bit]


_STATE_ITEMS = (
    "torque_enable",
    "hardware_error_status",
    "goal_position",
    "moving",
    "moving_status",
    "present_current",
    "present_velocity",
    "present_position",
    "present_input_voltage",
    "present_temperature",
)
_RAD_S_PER_VELOCITY_UNIT = ct.RPM_PER_VELOCITY_UNIT * 2 * math.pi / 60


def _state_struct(model: ct.ServoModel) -> struct.Struct:
    codes = {1: "B", 2: "H", 4: "I"}
    fmt, at = "<", ct.STATE_BLOCK_START
    for name in _STATE_ITEMS:
        r = model[name]
        if r.address < at:
            raise ValueError(f"state items out of address order at {name}")
        fmt += f"{r.address - at}x" if r.address > at else ""
        code = codes[r.size]
        fmt += code.lower() if r.signed else code
        at = r.address + r.size
    return struct.Struct(fmt + f"{ct.STATE_BLOCK_END - at}x")


class Servo:
    """One configured servo on a transport.

    Parameters
    ----------
    transport
        The bus (dynamixel-sdk :class:`~gonio.rig.transport.Transport`, or a loopback).
    config
        ID, model, joint, gear ratio, direction, zero and limits.
    """

    def __init__(self, transport: BusTransport, config: ServoConfig) -> None:
        self.bus = transport
        self.config = config
        self.id = config.id
        self.joint = config.joint
        model = ct.MODELS.get(config.model)
        if model is None:
            raise RigError(
                f"servo {config.id}: unknown model {config.model!r}; known: {sorted(ct.MODELS)}"
            )
        self.model = model
        # One precompiled little-endian decoder of the state block (decoded every cycle):
        # the items below in address order, pad bytes between them.
        self._block = _state_struct(model)
        # joint = direction * (pulses - zero) * 2 pi / 4096 / gear (ServoConfig.joint_rad)
        self._zero = config.zero_deg * ct.PULSES_PER_TURN / 360.0
        self._scale = config.direction * ct.RAD_PER_PULSE / config.gear_ratio
        self._vel_scale = config.direction * _RAD_S_PER_VELOCITY_UNIT / config.gear_ratio

    # ---------------------------------------------------------- conversions
    def to_pulses(self, joint_rad: float) -> int:
        """Goal Position (pulses) for a joint angle (rad).

        Raises
        ------
        PoseRefused
            ``RefusalReason.JOINT_LIMIT`` outside the servo's configured limits (or not
            finite).
        """
        lo, hi = self.config.limits_rad
        if not (lo - 1e-9 <= joint_rad <= hi + 1e-9) or not math.isfinite(joint_rad):
            raise PoseRefused(
                RefusalReason.JOINT_LIMIT,
                f"{self.joint} (servo {self.id}): {math.degrees(joint_rad):.3f} deg outside the "
                f"limits [{self.config.min_deg}, {self.config.max_deg}] deg",
            )
        return round(self.config.pulses(joint_rad))

    def to_joint(self, pulses: float) -> float:
        """Joint angle (rad) for a position count."""
        return self.config.joint_rad(pulses)

    def decode_state(self, block: bytes) -> ServoState:
        """Decode the cyclic block (``STATE_BLOCK_START`` .. ``STATE_BLOCK_END``)."""
        (torque, hw, goal, moving, mstatus, cur, vel, pos, volt, temp) = self._block.unpack_from(
            block
        )
        zero, scale = self._zero, self._scale
        return ServoState(
            self.id,
            self.joint,
            (pos - zero) * scale,
            (goal - zero) * scale,
            pos,
            goal,
            vel * self._vel_scale,
            cur * ct.AMPS_PER_CURRENT_UNIT,
            volt * ct.VOLTS_PER_VOLTAGE_UNIT,
            float(temp),
            bool(torque),
            bool(moving),
            bool(mstatus & 1),
            hw,
        )

    # ---------------------------------------------------------- register access
    def read(self, name: str) -> int:
        return self.bus.read(self.id, self.model[name])

    def write(self, name: str, value: int) -> None:
        self.bus.write(self.id, self.model[name], value)

    def state(self) -> ServoState:
        """Read and decode this servo's state block (one READ)."""
        return self.decode_state(
            self.bus.read_bytes(self.id, ct.STATE_BLOCK_START, ct.STATE_BLOCK_LEN)
        )

    def configure(self) -> None:
        """Write operating mode, position limits and motion profile; read them back.

        Only values that differ are written.  EEPROM items (mode, limits) need torque off,
        so torque is cut first when one of them must change; otherwise a servo holding
        its position keeps holding.  Raises RigError if a value does not stick.
        """
        c = self.config
        mode = ct.OPERATING_MODES[c.operating_mode]
        speed = math.radians(c.velocity_deg_s) * c.gear_ratio
        accel = math.radians(c.acceleration_deg_s2) * c.gear_ratio
        wanted = {"operating_mode": mode, "drive_mode": 0}  # direction is handled here
        if c.operating_mode == "position":
            lo, hi = sorted(
                (round(c.pulses(math.radians(c.min_deg))), round(c.pulses(math.radians(c.max_deg))))
            )
            wanted |= {"min_position_limit": max(0, lo), "max_position_limit": min(4095, hi)}
        wanted |= {
            "profile_velocity": ct.velocity_register(speed),
            "profile_acceleration": ct.acceleration_register(accel),
        }
        for name, v in wanted.items():
            if self.read(name) != v:
                if self.model[name].eeprom and self.read("torque_enable"):
                    self.torque(False)
                self.write(name, v)
                back = self.read(name)
                if back != v:
                    raise RigError(f"servo {self.id}: {name} reads back {back} after writing {v}")

    def torque(self, on: bool) -> None:
        self.write("torque_enable", int(on))
