"""The Dynamixel X-series control table, declared once.

The controller (:mod:`gonio.rig.transport`, :mod:`gonio.rig.servo`) and the virtual bus
(:mod:`gonio.simulator.virtual_bus`) both read their addresses, sizes, access rules,
signedness and defaults from here, so the two cannot drift apart.  Values follow the
ROBOTIS e-manual page of the XM430-W350 (see ``shared/reference/dynamixel.md``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

EEPROM_END = 64  # addresses below are EEPROM: writable only with torque off

PULSES_PER_TURN = 4096
RAD_PER_PULSE = 2 * math.pi / PULSES_PER_TURN
RPM_PER_VELOCITY_UNIT = 0.229
RPM2_PER_ACCELERATION_UNIT = 214.577
AMPS_PER_CURRENT_UNIT = 2.69e-3
VOLTS_PER_VOLTAGE_UNIT = 0.1

# Hardware Error Status (register 70) bits.
HW_INPUT_VOLTAGE = 0x01
HW_OVERHEATING = 0x04
HW_MOTOR_ENCODER = 0x08
HW_ELECTRICAL_SHOCK = 0x10
HW_OVERLOAD = 0x20
HW_ERROR_NAMES = {
    HW_INPUT_VOLTAGE: "input voltage",
    HW_OVERHEATING: "overheating",
    HW_MOTOR_ENCODER: "motor encoder",
    HW_ELECTRICAL_SHOCK: "electrical shock",
    HW_OVERLOAD: "overload",
}

OPERATING_MODES = {
    "current": 0,
    "velocity": 1,
    "position": 3,
    "extended_position": 4,
    "current_based_position": 5,
    "pwm": 16,
}
BAUD_CODES = {
    0: 9600,
    1: 57600,
    2: 115200,
    3: 1_000_000,
    4: 2_000_000,
    5: 3_000_000,
    6: 4_000_000,
    7: 4_500_000,
}


@dataclass(frozen=True)
class Register:
    """One control-table item.

    Attributes
    ----------
    name, address, size
        Item name, first byte address, size in bytes (1, 2 or 4).
    access
        ``"R"`` or ``"RW"``.
    default
        Value after factory reset (None for live read-only values).
    signed
        Whether the raw value is two's complement.
    low, high
        Inclusive range a WRITE must respect (None: the full width of the item).
    """

    name: str
    address: int
    size: int
    access: str = "RW"
    default: int | None = 0
    signed: bool = False
    low: int | None = None
    high: int | None = None

    @property
    def eeprom(self) -> bool:
        return self.address < EEPROM_END

    def to_signed(self, raw: int) -> int:
        """Unsigned raw bytes (as dynamixel-sdk returns them) -> the item's value."""
        raw &= (1 << (8 * self.size)) - 1
        if self.signed and raw >= 1 << (8 * self.size - 1):
            return raw - (1 << (8 * self.size))
        return raw

    def to_raw(self, value: int) -> int:
        """The item's value -> unsigned raw integer for the wire."""
        return int(value) & ((1 << (8 * self.size)) - 1)


def _r(*args, **kw) -> Register:
    return Register(*args, **kw)


# XM430-W350 (and XM430-W210, XM/XH430 share the layout).
XM430_REGISTERS: tuple[Register, ...] = (
    _r("model_number", 0, 2, "R", 1020),
    _r("model_information", 2, 4, "R", 0),
    _r("firmware_version", 6, 1, "R", 45),
    _r("id", 7, 1, default=1, low=0, high=252),
    _r("baud_rate", 8, 1, default=1, low=0, high=7),
    _r("return_delay_time", 9, 1, default=250, low=0, high=254),
    _r("drive_mode", 10, 1, default=0, low=0, high=13),
    _r("operating_mode", 11, 1, default=3, low=0, high=16),
    _r("secondary_id", 12, 1, default=255, low=0, high=255),
    _r("protocol_type", 13, 1, default=2, low=1, high=2),
    _r("homing_offset", 20, 4, default=0, signed=True, low=-1_044_479, high=1_044_479),
    _r("moving_threshold", 24, 4, default=10, low=0, high=1023),
    _r("temperature_limit", 31, 1, default=80, low=0, high=100),
    _r("max_voltage_limit", 32, 2, default=160, low=95, high=160),
    _r("min_voltage_limit", 34, 2, default=95, low=95, high=160),
    _r("pwm_limit", 36, 2, default=885, low=0, high=885),
    _r("current_limit", 38, 2, default=1193, low=0, high=1193),
    _r("velocity_limit", 44, 4, default=200, low=0, high=1023),
    _r("max_position_limit", 48, 4, default=4095, low=0, high=4095),
    _r("min_position_limit", 52, 4, default=0, low=0, high=4095),
    _r("startup_configuration", 60, 1, default=0, low=0, high=3),
    _r("shutdown", 63, 1, default=0x34, low=0, high=0xFF),
    _r("torque_enable", 64, 1, default=0, low=0, high=1),
    _r("led", 65, 1, default=0, low=0, high=1),
    _r("status_return_level", 68, 1, default=2, low=0, high=2),
    _r("registered_instruction", 69, 1, "R", 0),
    _r("hardware_error_status", 70, 1, "R", 0),
    _r("velocity_i_gain", 76, 2, default=1920, low=0, high=16383),
    _r("velocity_p_gain", 78, 2, default=100, low=0, high=16383),
    _r("position_d_gain", 80, 2, default=0, low=0, high=16383),
    _r("position_i_gain", 82, 2, default=0, low=0, high=16383),
    _r("position_p_gain", 84, 2, default=800, low=0, high=16383),
    _r("bus_watchdog", 98, 1, default=0, low=0, high=127),
    _r("goal_pwm", 100, 2, default=0, signed=True, low=-885, high=885),
    _r("goal_current", 102, 2, default=0, signed=True, low=-1193, high=1193),
    _r("goal_velocity", 104, 4, default=0, signed=True, low=-200, high=200),
    _r("profile_acceleration", 108, 4, default=0, low=0, high=32767),
    _r("profile_velocity", 112, 4, default=0, low=0, high=32767),
    _r("goal_position", 116, 4, default=0, signed=True, low=-1_048_575, high=1_048_575),
    _r("realtime_tick", 120, 2, "R", 0),
    _r("moving", 122, 1, "R", 0),
    _r("moving_status", 123, 1, "R", 0),
    _r("present_pwm", 124, 2, "R", 0, signed=True),
    _r("present_current", 126, 2, "R", 0, signed=True),
    _r("present_velocity", 128, 4, "R", 0, signed=True),
    _r("present_position", 132, 4, "R", 0, signed=True),
    _r("velocity_trajectory", 136, 4, "R", 0, signed=True),
    _r("position_trajectory", 140, 4, "R", 0, signed=True),
    _r("present_input_voltage", 144, 2, "R", 120),
    _r("present_temperature", 146, 1, "R", 30),
)


@dataclass(frozen=True)
class ServoModel:
    """An X-series model: its number, control table and mechanics.

    Attributes
    ----------
    name, number
        Model name (``"XM430-W350"``) and the Model Number register value.
    registers
        Control table items by name.
    max_speed_rpm
        No-load speed at 12 V: what a Profile Velocity of 0 ("no limit") gives.
    """

    name: str
    number: int
    registers: dict[str, Register]
    max_speed_rpm: float
    control_table_size: int = 147

    def __getitem__(self, name: str) -> Register:
        return self.registers[name]

    def at(self, address: int) -> Register | None:
        """The item starting at ``address``, if any."""
        return _BY_ADDRESS[self.name].get(address)


def _model(name: str, number: int, max_speed_rpm: float) -> ServoModel:
    regs = {r.name: r for r in XM430_REGISTERS}
    regs["model_number"] = Register("model_number", 0, 2, "R", number)
    return ServoModel(name, number, regs, max_speed_rpm)


MODELS: dict[str, ServoModel] = {
    m.name: m
    for m in (
        _model("XM430-W350", 1020, 46.0),
        _model("XM430-W210", 1030, 77.0),
        _model("XH430-W350", 1010, 46.0),
    )
}
MODELS_BY_NUMBER: dict[int, ServoModel] = {m.number: m for m in MODELS.values()}
_BY_ADDRESS = {m.name: {r.address: r for r in m.registers.values()} for m in MODELS.values()}

# The block the controller sync-reads every cycle, one contiguous transaction: torque
# enable (64), Hardware Error Status (70: group reads drop the ERR byte's alert bit, so it
# must be read), goal (116), moving / moving status, current, velocity, position,
# voltage and temperature (up to 146).
STATE_BLOCK_START = 64
STATE_BLOCK_END = 147
STATE_BLOCK_LEN = STATE_BLOCK_END - STATE_BLOCK_START


def velocity_register(speed_rad_s: float) -> int:
    """Profile Velocity register value (0.229 rpm units) for a servo speed (rad/s).

    0 means "no limit"; a positive speed never rounds to 0.
    """
    if speed_rad_s <= 0:
        return 0
    rpm = speed_rad_s * 60 / (2 * math.pi)
    return max(1, round(rpm / RPM_PER_VELOCITY_UNIT))


def acceleration_register(accel_rad_s2: float) -> int:
    """Profile Acceleration register value (214.577 rev/min^2 units) for rad/s^2."""
    if accel_rad_s2 <= 0:
        return 0
    rpm2 = accel_rad_s2 * 3600 / (2 * math.pi)
    return max(1, round(rpm2 / RPM2_PER_ACCELERATION_UNIT))


def profile_pulses(
    velocity_reg: int, acceleration_reg: int, model: ServoModel
) -> tuple[float, float]:
    """(speed pulses/s, acceleration pulses/s^2) of a velocity-based profile.

    Profile Velocity 0 -> the model's no-load speed; Profile Acceleration 0 -> infinite.
    """
    rpm = velocity_reg * RPM_PER_VELOCITY_UNIT if velocity_reg > 0 else model.max_speed_rpm
    v = rpm * PULSES_PER_TURN / 60.0
    a = acceleration_reg * RPM2_PER_ACCELERATION_UNIT * PULSES_PER_TURN / 3600.0
    return v, (a if acceleration_reg > 0 else math.inf)
