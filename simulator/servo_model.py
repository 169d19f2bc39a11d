"""One virtual X-series servo: control table memory, access rules, motion and faults.

The register layout comes from :mod:`gonio.rig.control_table` (declared once).  Motion
follows the goal on a trapezoid from Profile Velocity / Profile Acceleration; it is
computed on demand from the bus's servo clock (no thread per servo): a scaled wall clock,
or a virtual one that jumps to the end of a polled move (:mod:`gonio.simulator.servo_clock`).
Current follows load crudely.  The motor heats while it moves, towards 12 degC above
ambient with a time constant of 60 s of *motion* time, and keeps its temperature at rest:
the temperature is a function of the commanded moves alone (each accounted exactly from
its own start and duration, not from when it is polled), so a virtual-time session reads
the same temperatures as a watched one.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from gonio.rig import control_table as ct
from gonio.rig.protocol import (
    ERR_ACCESS,
    ERR_ALERT,
    ERR_DATA_LENGTH,
    ERR_DATA_LIMIT,
    from_le,
    le,
)

TABLE_SIZE = 662  # XM430 control table incl. indirect address/data (plain RAM here)
_AMBIENT_C = 30.0
_HEAT_MOVING_C = 12.0  # steady rise above ambient of a motor that never stops, degC
_HEAT_TAU_S = 60.0  # heating time constant, s of motion
_BACKLASH_TAKE_UP_PULSES = 1  # a longer move puts the joint on its side of the backlash


def _heated(heat: float, moving_s: float) -> float:
    """Rise above ambient (degC) after ``moving_s`` seconds of motion starting at ``heat``."""
    return _HEAT_MOVING_C + (heat - _HEAT_MOVING_C) * math.exp(-moving_s / _HEAT_TAU_S)


def _trapezoid(d: float, v: float, a: float, t: float) -> tuple[float, float, float]:
    """(distance covered, speed, total time) at time ``t`` of a rest-to-rest move of ``d``.

    Written independently of the controller's move-time estimate so that tests of one
    check the other.
    """
    if d <= 0:
        return 0.0, 0.0, 0.0
    if math.isinf(a):
        total = d / v
        return (min(d, v * t), v if t < total else 0.0, total)
    t_ramp = v / a
    if a * t_ramp * t_ramp >= d:  # never reaches cruise speed: triangle
        t_ramp = math.sqrt(d / a)
        v = a * t_ramp
        total = 2 * t_ramp
    else:
        total = t_ramp + d / v
    if t <= 0:
        return 0.0, 0.0, total
    if t >= total:
        return d, 0.0, total
    if t < t_ramp:
        return 0.5 * a * t * t, a * t, total
    if t > total - t_ramp:
        r = total - t
        return d - 0.5 * a * r * r, a * r, total
    return 0.5 * a * t_ramp * t_ramp + v * (t - t_ramp), v, total


@dataclass
class _Segment:
    t0: float  # bus clock (scaled seconds) when the move started
    p0: float
    p1: float
    speed: float  # pulses/s
    accel: float  # pulses/s^2 (inf: no ramp)


class VirtualServo:
    """A servo's memory and physics.

    Parameters
    ----------
    dxl_id
        Bus ID.
    model
        Model name from :data:`gonio.rig.control_table.MODELS`.
    firmware
        Firmware Version register value.
    clock
        The servo clock (s), shared by the servos of a bus (the bus sets it).
    position
        Initial Present Position (pulses).
    landing_pulses
        As built: a move ends within +-``landing_pulses`` of its goal (the encoder
        reports where it ended); 0 lands exactly.
    landing_seed
        Seed of the landing errors: move ``n`` of servo ``id`` draws its error from
        ``default_rng([landing_seed, id, n])``, so a session is reproducible.
    last_direction
        Sign of the horn's last move before this servo was made (pulses: +1, -1, 0
        unknown): which side of its backlash the gear train rests on.
    """

    def __init__(
        self,
        dxl_id: int,
        model: str = "XM430-W350",
        firmware: int = 45,
        clock: Callable[[], float] = time.monotonic,
        position: int = 2048,
        *,
        landing_pulses: int = 0,
        landing_seed: int = 0,
        last_direction: int = 0,
    ) -> None:
        self.model = ct.MODELS[model]
        self.firmware = firmware
        self.clock = clock
        self.mem = bytearray(TABLE_SIZE)
        self.lock = threading.RLock()
        self.silent = False  # a servo that stops answering
        self.pending_fault: tuple[int, float] | None = None  # (bits, fraction of next move)
        self.voltage_raw = 120
        self._reset_all()
        self.set_u("id", dxl_id)
        self._pos = float(position)
        self._seg: _Segment | None = None
        self._fault_at: tuple[float, int] | None = None
        self._heat = 0.0  # degC above ambient when the present segment (if any) started
        self.registered: tuple[int, bytes] | None = None
        self.torque_log: list[tuple[float, int]] = []  # (clock, torque) for tests and audits
        self.landing_pulses = int(landing_pulses)
        self.landing_seed = int(landing_seed)
        self._moves = 0  # moves with a landing error drawn so far
        # Physical state, not memory: kept through REBOOT (the gears stay where they are).
        self._last_direction = int(np.sign(last_direction))

    # ------------------------------------------------------------- raw memory
    def _reset_all(self, keep: tuple[str, ...] = ()) -> None:
        saved = {n: self.get_u(n) for n in keep}
        self.mem[:] = bytes(TABLE_SIZE)
        for r in self.model.registers.values():
            if r.default is not None:
                self.mem[r.address : r.address + r.size] = le(r.default, r.size)
        self.set_u("firmware_version", self.firmware)
        # indirect addresses default to their own data slots (plain RAM behaviour)
        for n, v in saved.items():
            self.set_u(n, v)

    def get_u(self, name: str) -> int:
        r = self.model[name]
        return from_le(self.mem[r.address : r.address + r.size])

    def get(self, name: str) -> int:
        """Signed value of a register (after bringing the physics up to date)."""
        with self.lock:
            self._update()
            return self.model[name].to_signed(self.get_u(name))

    def set_u(self, name: str, value: int) -> None:
        r = self.model[name]
        self.mem[r.address : r.address + r.size] = le(value, r.size)

    @property
    def dxl_id(self) -> int:
        return self.get_u("id")

    # ------------------------------------------------------------- physics
    def _profile(self) -> tuple[float, float]:
        return ct.profile_pulses(
            self.get_u("profile_velocity"), self.get_u("profile_acceleration"), self.model
        )

    def _position_at(self, t: float) -> tuple[float, float, bool]:
        seg = self._seg
        if seg is None:
            return self._pos, 0.0, False
        d = abs(seg.p1 - seg.p0)
        covered, speed, total = _trapezoid(d, seg.speed, seg.accel, t - seg.t0)
        sign = 1.0 if seg.p1 >= seg.p0 else -1.0
        return seg.p0 + sign * covered, sign * speed, t - seg.t0 < total

    def _segment_total(self) -> float:
        seg = self._seg
        assert seg is not None
        return _trapezoid(abs(seg.p1 - seg.p0), seg.speed, seg.accel, 0.0)[2]

    def _heat_at(self, t: float) -> float:
        """Rise above ambient (degC) at servo time ``t``: the present segment's motion
        up to ``t`` on top of the heat it started with."""
        if self._seg is None:
            return self._heat
        return _heated(self._heat, min(max(t - self._seg.t0, 0.0), self._segment_total()))

    def _end_segment(self, t: float, pos: float) -> None:
        """Stop the present segment at servo time ``t`` at ``pos``, its heat accounted."""
        self._heat = self._heat_at(t)
        # A move of one pulse (0.09 deg) cannot carry a joint across a backlash of a
        # quarter degree: only a longer one puts it on the other side (a landing error
        # never asks for such a move: a goal within the landing band does not move).
        if self._seg is not None and abs(pos - self._seg.p0) > _BACKLASH_TAKE_UP_PULSES:
            self._last_direction = 1 if pos > self._seg.p0 else -1
        self._pos, self._seg = pos, None

    def motion_end(self) -> float | None:
        """Servo time (s) at which the commanded move ends, None when not moving."""
        with self.lock:
            if self._seg is None:
                return None
            t0, total = self._seg.t0, self._segment_total()
            end = t0 + total
            while end - t0 < total:  # rounding: at ``end`` the move must be over
                end = math.nextafter(end, math.inf)
            return end

    def _update(self) -> None:
        now = self.clock()
        if self._fault_at is not None and now >= self._fault_at[0]:
            t_fault, bits = self._fault_at
            self._fault_at = None
            if self._seg is not None:
                self._end_segment(t_fault, self._position_at(t_fault)[0])
            self._trip(bits)
        pos, speed, moving = self._position_at(now)
        if self._seg is not None and not moving:
            self._end_segment(now, self._seg.p1)
            pos = self._pos
        elif self._seg is not None:
            self._pos = pos
        torque = self.get_u("torque_enable")
        # Current: holding + acceleration share while moving (crude, in 2.69 mA units).
        load = (120 if moving else 15) if torque else 0
        present = round(pos)
        self.set_u("present_position", le_int(present, 4))
        self.set_u(
            "present_velocity", le_int(round(speed * 60 / 4096 / ct.RPM_PER_VELOCITY_UNIT), 4)
        )
        self.set_u("present_current", le_int(load if speed >= 0 else -load, 2))
        temperature = int(round(_AMBIENT_C + self._heat_at(now)))
        self.set_u("present_temperature", temperature)
        if temperature > self.get_u("temperature_limit"):
            self._trip(ct.HW_OVERHEATING)
        self.set_u("present_input_voltage", self.voltage_raw)
        goal = self.model["goal_position"].to_signed(self.get_u("goal_position"))
        in_pos = abs(goal - present) <= 1 or not torque
        self.set_u("moving", int(moving))
        self.set_u("moving_status", (1 if in_pos else 0) | (2 if moving else 0))
        self.set_u("realtime_tick", int(now * 1000) % 32768)

    def _trip(self, bits: int) -> None:
        self.set_u("hardware_error_status", self.get_u("hardware_error_status") | bits)
        if bits & self.get_u("shutdown"):
            self._set_torque(0)

    def _set_torque(self, value: int) -> None:
        if value == 0 and self._seg is not None:
            now = self.clock()
            self._end_segment(now, self._position_at(now)[0])
        self.set_u("torque_enable", value)
        self.torque_log.append((self.clock(), value))

    def _start_move(self, goal: int) -> None:
        now = self.clock()
        pos, _, _ = self._position_at(now)
        if self._seg is not None:  # a new goal mid-move: the motion so far has heated
            self._end_segment(now, pos)
        self._pos = pos
        v, a = self._profile()
        target = float(goal)
        if self.landing_pulses and abs(goal - pos) > self.landing_pulses:
            # A real servo stops within a pulse or so of its goal (its deadband); the
            # encoder reports where.  A goal already within that band does not move it.
            rng = np.random.default_rng([self.landing_seed, self.dxl_id, self._moves])
            self._moves += 1
            target += int(rng.integers(-self.landing_pulses, self.landing_pulses + 1))
        elif self.landing_pulses:
            target = pos
        self._seg = _Segment(now, pos, target, v, a)
        if self.pending_fault is not None:
            bits, frac = self.pending_fault
            self.pending_fault = None
            _, _, total = _trapezoid(abs(goal - pos), v, a, 0.0)
            self._fault_at = (now + frac * total, bits)

    # ------------------------------------------------------------- test hooks
    def set_position(self, pulses: int) -> None:
        """Place the horn at ``pulses`` (as if turned by hand with torque off)."""
        with self.lock:
            if self._seg is not None:
                self._end_segment(self.clock(), float(pulses))
            self._pos, self._seg = float(pulses), None
            self._update()

    def set_temperature(self, celsius: float) -> None:
        """Make the resting motor ``celsius`` degC warm (as if from earlier work); it
        keeps that temperature until it moves."""
        with self.lock:
            self._update()
            if self._seg is not None:
                raise RuntimeError(f"servo {self.dxl_id} is moving: set its temperature at rest")
            self._heat = float(celsius) - _AMBIENT_C
            self._update()

    def inject_fault(self, bits: int, during_next_move: float | None = None) -> None:
        """Trip hardware error ``bits`` now, or at a fraction of the next move's duration."""
        with self.lock:
            if during_next_move is None:
                self._update()
                self._trip(bits)
            else:
                self.pending_fault = (bits, during_next_move)

    @property
    def temperature_c(self) -> float:
        """Motor temperature (degC, unrounded; the register holds it rounded)."""
        with self.lock:
            self._update()
            return _AMBIENT_C + self._heat_at(self.clock())

    @property
    def last_direction(self) -> int:
        """Sign of the horn's last motion in pulses (+1, -1; 0 never moved): the side of
        its backlash the gear train rests on (physical truth, not a register)."""
        with self.lock:
            self._update()
            return self._last_direction

    def true_state(self) -> tuple[int, int]:
        """(Present Position in pulses, :attr:`last_direction`), read together."""
        with self.lock:
            self._update()
            return self.model["present_position"].to_signed(
                self.get_u("present_position")
            ), self._last_direction

    @property
    def alert(self) -> bool:
        return self.get_u("hardware_error_status") != 0

    # ------------------------------------------------------------- instructions
    def error_byte(self, err: int = 0) -> int:
        return err | (ERR_ALERT if self.alert else 0)

    def read(self, address: int, length: int) -> tuple[int, bytes]:
        """READ: (error, data)."""
        with self.lock:
            self._update()
            if length < 0 or address + length > TABLE_SIZE:
                return self.error_byte(ERR_ACCESS), b""
            return self.error_byte(), bytes(self.mem[address : address + length])

    def check_write(self, address: int, data: bytes) -> int:
        """Error code a WRITE of ``data`` at ``address`` would get (0: fine)."""
        end = address + len(data)
        if not data:
            return ERR_DATA_LENGTH
        if end > TABLE_SIZE:
            return ERR_ACCESS
        torque = self.get_u("torque_enable")
        for r in self.model.registers.values():
            if r.address + r.size <= address or r.address >= end:
                continue
            if r.access == "R":
                return ERR_ACCESS
            if r.eeprom and torque:
                return ERR_ACCESS
            if r.address >= address and r.address + r.size <= end:
                raw = from_le(data[r.address - address : r.address - address + r.size])
                value = r.to_signed(raw)
                if r.name == "torque_enable" and value == 1 and self.alert:
                    return ERR_ACCESS  # after a shutdown only REBOOT re-enables torque
                if r.name == "goal_position" and self.get_u("operating_mode") == 3:
                    lo, hi = self.get_u("min_position_limit"), self.get_u("max_position_limit")
                    if not lo <= value <= hi:
                        return ERR_DATA_LIMIT
                elif r.low is not None and not r.low <= value <= r.high:
                    return ERR_DATA_LIMIT
            else:
                return ERR_DATA_LENGTH  # a write that covers part of a multi-byte item
        return 0

    def write(self, address: int, data: bytes) -> int:
        """WRITE: apply ``data`` unless invalid; returns the status ERR byte."""
        with self.lock:
            self._update()
            err = self.check_write(address, data)
            if err:
                return self.error_byte(err)
            end = address + len(data)
            old_torque = self.get_u("torque_enable")
            self.mem[address:end] = data
            if address <= 64 < end:
                new = self.mem[64]
                self.set_u("torque_enable", old_torque)
                self._set_torque(new)
            gp = self.model["goal_position"].address
            if address <= gp < end and self.get_u("torque_enable"):
                self._start_move(self.model["goal_position"].to_signed(self.get_u("goal_position")))
            elif address <= 64 < end and self.get_u("torque_enable") and not old_torque:
                self._start_move(self.model["goal_position"].to_signed(self.get_u("goal_position")))
            self._update()
            return self.error_byte()

    def reg_write(self, address: int, data: bytes) -> int:
        with self.lock:
            err = self.check_write(address, data)
            if err:
                return self.error_byte(err)
            self.registered = (address, bytes(data))
            self.set_u("registered_instruction", 1)
            return self.error_byte()

    def action(self) -> int:
        with self.lock:
            if self.registered is None:
                return self.error_byte()
            address, data = self.registered
            self.registered = None
            self.set_u("registered_instruction", 0)
            return self.write(address, data)

    def reboot(self) -> int:
        with self.lock:
            self._update()
            if self._seg is not None:
                self._end_segment(self.clock(), self._pos)
            self._fault_at = None
            self._reset_all(keep=_EEPROM_NAMES)
            self.torque_log.append((self.clock(), 0))
            self._update()
            return self.error_byte()

    def factory_reset(self, option: int) -> int:
        with self.lock:
            if self.get_u("torque_enable"):
                return self.error_byte(ERR_ACCESS)
            keep = {0xFF: (), 0x01: ("id",), 0x02: ("id", "baud_rate")}.get(option)
            if keep is None:
                return self.error_byte(ERR_DATA_LIMIT)
            self._reset_all(keep=keep)
            self._update()
            return self.error_byte()

    def clear_multi_turn(self) -> int:
        with self.lock:
            self._update()
            if self._seg is not None:
                return self.error_byte(ERR_ACCESS)
            self._pos = float(int(round(self._pos)) % ct.PULSES_PER_TURN)
            self._update()
            return self.error_byte()

    def ping_data(self) -> bytes:
        return le(self.get_u("model_number"), 2) + bytes([self.firmware])


def le_int(value: int, size: int) -> int:
    """Two's complement raw integer of a signed value."""
    return int(value) & ((1 << (8 * size)) - 1)


_EEPROM_NAMES = tuple(r.name for r in ct.XM430_REGISTERS if r.eeprom and r.access == "RW")
