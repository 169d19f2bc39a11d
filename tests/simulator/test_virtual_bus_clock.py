"""Virtual servo time: polled motion and settle times advance the servos' clock.

Move durations are checked against the trapezoid written out here from the e-manual's
unit definitions (Profile Velocity 0.229 rev/min, Profile Acceleration 214.577 rev/min^2)
and against the controller's own estimate (``Kinematics.move_time``); heating against its
closed form; the wire against dynamixel-sdk's wall-clock timeouts.
"""

from __future__ import annotations

import math
import sys

import pytest
from dynamixel_sdk import COMM_RX_TIMEOUT, COMM_SUCCESS, PacketHandler, PortHandler

from gonio.radiometry.frames import spherical_to_direction
from gonio.rig import control_table as ct
from gonio.rig import protocol as p
from gonio.rig.config import default_rig_config
from gonio.rig.device import Rig
from gonio.simulator.loopback import LoopbackTransport
from gonio.simulator.servo_clock import (
    ScaledClock,
    VirtualClock,
    make_clock,
    parse_time_scale,
)
from gonio.simulator.virtual_bus import ServoBus, VirtualBus

XM430 = ct.MODELS["XM430-W350"]


def manual_trapezoid_s(d: float, velocity_reg: int, accel_reg: int) -> float:
    """Duration (s) of a rest-to-rest move of ``d`` pulses, from the e-manual's units."""
    v = velocity_reg * 0.229 * 4096 / 60  # pulses/s
    a = accel_reg * 214.577 * 4096 / 3600  # pulses/s^2
    if v * v / a < d:  # reaches cruise speed
        return d / v + v / a
    return 2 * math.sqrt(d / a)


def manual_position(d: float, velocity_reg: int, accel_reg: int, t: float) -> float:
    """Pulses covered at ``t`` (s) of that move (cruise-speed case)."""
    v = velocity_reg * 0.229 * 4096 / 60
    a = accel_reg * 214.577 * 4096 / 3600
    ramp = v / a
    assert v * ramp < d and ramp < t < d / v  # in the cruise phase
    return 0.5 * a * ramp * ramp + v * (t - ramp)


@pytest.fixture
def wire():
    """Loopback transport into a two-servo virtual-time bus, torque on, profiles set."""
    t = LoopbackTransport([1, 2], time_scale="virtual").open()
    for i in (1, 2):
        t.write(i, XM430["profile_velocity"], 100)
        t.write(i, XM430["profile_acceleration"], 50)
        t.write(i, XM430["goal_position"], 2048)  # hold where it is when torque comes on
        t.write(i, XM430["torque_enable"], 1)
    return t


def test_a_polled_move_is_over_at_the_end_of_its_trapezoid(wire):
    bus = wire.bus
    assert bus.virtual and bus.time_scale == "virtual"
    t0 = bus.clock()
    wire.write(1, XM430["goal_position"], 3048)  # 1000 pulses from the centre
    assert bus.clock() == t0  # a write takes no servo time
    assert wire.read(1, XM430["present_position"]) == 3048  # the first poll sees it there
    assert wire.read(1, XM430["moving"]) == 0
    assert bus.clock() - t0 == pytest.approx(manual_trapezoid_s(1000, 100, 50), rel=1e-9)


def test_only_the_polled_servos_motion_is_waited_for(wire):
    bus = wire.bus
    t0 = bus.clock()
    wire.sync_write(XM430["goal_position"], {1: 2348, 2: 3548})  # 300 and 1500 pulses
    assert wire.read(1, XM430["present_position"]) == 2348
    short = manual_trapezoid_s(300, 100, 50)
    assert bus.clock() - t0 == pytest.approx(short, rel=1e-9)
    blocks = wire.sync_read([1, 2], XM430["present_position"].address, 4)
    assert [p.from_le(b) for b in blocks.values()] == [2348, 3548]
    assert bus.clock() - t0 == pytest.approx(manual_trapezoid_s(1500, 100, 50), rel=1e-9)


def test_servo_two_is_seen_mid_move_when_only_servo_one_was_polled(wire):
    bus = wire.bus
    t0 = bus.clock()
    wire.sync_write(XM430["goal_position"], {1: 2348, 2: 3548})
    wire.read(1, XM430["present_position"])
    short = manual_trapezoid_s(300, 100, 50)
    # read the servo's memory without a bus instruction: no catching up
    mid = bus.servos[2].get("present_position")
    assert mid == round(2048 + manual_position(1500, 100, 50, bus.clock() - t0))
    assert bus.clock() - t0 == pytest.approx(short, rel=1e-9)
    assert bus.servos[2].get("moving") == 1


def test_a_fault_due_mid_move_stops_the_servo_where_it_was_then(wire):
    bus = wire.bus
    bus.servos[1].inject_fault(ct.HW_OVERLOAD, during_next_move=0.5)
    wire.write(1, XM430["goal_position"], 3048)
    # half way in time is half way in distance on a symmetric trapezoid
    assert wire.read(1, XM430["present_position"]) == 2548
    assert wire.read(1, XM430["hardware_error_status"]) == ct.HW_OVERLOAD
    assert wire.read(1, XM430["torque_enable"]) == 0  # the default Shutdown includes overload


def test_sleep_adds_servo_time_at_once_and_moves_nothing(wire):
    bus = wire.bus
    t0, pos = bus.clock(), bus.servos[1].get("present_position")
    wire.sleep(2.5)
    wire.sleep(-1.0)  # a negative settle time does nothing
    assert bus.clock() - t0 == 2.5
    assert bus.servos[1].get("present_position") == pos


def test_heating_follows_the_motion_not_the_polling():
    """The same crawl polled once or 400 times heats the motor to the same temperature:
    the closed form of the first-order model over the move's duration."""

    def crawl(polls: int) -> tuple[float, float]:
        t = LoopbackTransport([1], time_scale="virtual").open()
        t.write(1, XM430["profile_velocity"], 1)  # 15.6 pulses/s: a two-minute move
        t.write(1, XM430["profile_acceleration"], 0)  # no ramp
        t.write(1, XM430["goal_position"], 2048)
        t.write(1, XM430["torque_enable"], 1)
        t.write(1, XM430["goal_position"], 4000)
        total = 1952 / (0.229 * 4096 / 60)
        for _ in range(polls):
            t.sleep(total / polls * 0.999)
            t.bus.servos[1].get("present_temperature")
        t.read(1, XM430["present_position"])
        servo = t.bus.servos[1]
        return servo.temperature_c, t.bus.clock()

    once, t_once = crawl(0)
    often, _ = crawl(400)
    assert once == often
    assert t_once == pytest.approx(1952 / (0.229 * 4096 / 60), rel=1e-9)
    assert once == pytest.approx(30.0 + 12.0 * (1 - math.exp(-t_once / 60.0)), rel=1e-12)


def test_a_resting_motor_keeps_its_temperature():
    bus = ServoBus([1], time_scale="virtual")
    s = bus.servos[1]
    s.set_temperature(36.0)
    bus.sleep(3600.0)
    assert s.temperature_c == 36.0 and s.get("present_temperature") == 36


def test_time_scales_are_parsed_and_refused_by_value():
    assert parse_time_scale("virtual") == parse_time_scale(" Virtual ") == "virtual"
    assert parse_time_scale("20") == 20.0 and parse_time_scale(2) == 2.0
    assert isinstance(make_clock("virtual"), VirtualClock)
    assert isinstance(make_clock(5.0), ScaledClock) and make_clock(5.0).time_scale == 5.0
    for bad in ("fast", 0, -1.0, math.nan, math.inf, None, 1e308):
        with pytest.raises(ValueError, match="'virtual' or a speed-up factor in"):
            parse_time_scale(bad)
    with pytest.raises(ValueError, match=r"speed-up factor in \(0, 1e\+06\], got 0.0"):
        ServoBus([1], time_scale=0.0)


def test_a_scaled_clock_is_not_moved_by_polls():
    clock = ScaledClock(1.0)
    before = clock.now()
    clock.catch_up(before + 3600.0)
    assert clock.now() < before + 3600.0


# ---------------------------------------------------------------------------- the pty
@pytest.fixture
def pty_bus():
    old = sys.getswitchinterval()
    sys.setswitchinterval(2e-4)  # the emulator thread shares the GIL with the busy SDK
    cfg = default_rig_config()
    with VirtualBus(list(cfg.park_pulses), time_scale="virtual", seed=0) as bus:
        for i, pulses in cfg.park_pulses.items():
            bus.servos[i].set_position(pulses)
        yield bus, cfg
    sys.setswitchinterval(old)


def test_the_rig_over_dynamixel_sdk_moves_in_servo_time(pty_bus):
    """Through the real SDK on the pty: each move is seen finished at the first poll
    after the goal, and lasts, in servo time, what the controller's estimate says."""
    bus, cfg = pty_bus
    with Rig(cfg, port=bus.port, clock=bus.clock) as rig:
        wi, wo = spherical_to_direction(0.5, 0.3), spherical_to_direction(0.6, 2.8)
        for _ in range(2):
            q0 = rig.joints()
            reads = bus.stats.instructions.get(p.SYNC_READ, 0)
            res = rig.move_to(wi, wo)
            # one state read before the goal, one poll after it: no waiting for motion
            assert bus.stats.instructions[p.SYNC_READ] - reads == 2
            expected = rig.kinematics.move_time(q0, res.joints)
            assert expected > 0.5
            assert res.duration == pytest.approx(expected, rel=1e-9)
            assert max(res.error_i, res.error_o) < math.radians(0.2)
            wi, wo = spherical_to_direction(0.3, -1.0), spherical_to_direction(0.7, 2.0)


def test_the_sdk_timeouts_stay_wall_clock(pty_bus):
    bus, _ = pty_bus
    port = PortHandler(bus.port)
    assert port.openPort() and port.setBaudRate(1_000_000)
    try:
        ph = PacketHandler(2.0)
        bus.servos[2].silent = True
        assert ph.ping(port, 2)[1] == COMM_RX_TIMEOUT  # a silent servo times out
        t = bus.clock()
        assert ph.read4ByteTxRx(port, 1, 132)[1] == COMM_SUCCESS
        bus.delay_rate, bus.delay_s = 1.0, 0.005  # late, within the SDK's timeout
        assert ph.read1ByteTxRx(port, 1, 68) == (2, COMM_SUCCESS, 0)
        assert bus.stats.delayed >= 1
        assert bus.clock() == t  # waiting on the wire is not servo time
    finally:
        port.closePort()
