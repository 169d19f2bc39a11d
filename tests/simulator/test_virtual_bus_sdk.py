"""The unmodified dynamixel-sdk talks to the virtual bus over the pty."""

from __future__ import annotations

import math
import sys
import threading

import pytest
from dynamixel_sdk import (
    COMM_RX_TIMEOUT,
    COMM_SUCCESS,
    GroupBulkRead,
    GroupBulkWrite,
    GroupSyncRead,
    GroupSyncWrite,
    PacketHandler,
    PortHandler,
)

from gonio.simulator.virtual_bus import VirtualBus


@pytest.fixture
def sdk():
    old = sys.getswitchinterval()
    sys.setswitchinterval(2e-4)  # the emulator thread shares the GIL with the busy-polling SDK
    with VirtualBus([1, 2, 3, 4], seed=0, time_scale=50.0) as bus:
        port = PortHandler(bus.port)
        assert port.openPort() and port.setBaudRate(1_000_000)
        yield bus, port, PacketHandler(2.0)
        port.closePort()
    sys.setswitchinterval(old)


def test_ping_read_write(sdk):
    bus, port, ph = sdk
    model, res, err = ph.ping(port, 3)
    assert (model, res, err) == (1020, COMM_SUCCESS, 0)
    assert ph.ping(port, 9)[1] == COMM_RX_TIMEOUT
    assert ph.read1ByteTxRx(port, 2, 6) == (45, COMM_SUCCESS, 0)  # firmware
    assert ph.write4ByteTxRx(port, 2, 112, 77) == (COMM_SUCCESS, 0)
    assert ph.read4ByteTxRx(port, 2, 112) == (77, COMM_SUCCESS, 0)
    # read-only and EEPROM-while-torque-on writes are refused with an access error
    assert ph.write2ByteTxRx(port, 2, 0, 5) == (COMM_SUCCESS, 7)
    assert ph.write1ByteTxRx(port, 2, 64, 1) == (COMM_SUCCESS, 0)
    assert ph.write1ByteTxRx(port, 2, 11, 4) == (COMM_SUCCESS, 7)
    assert ph.read1ByteTxRx(port, 2, 11)[0] == 3
    # out-of-range goal in position mode: data limit error
    assert ph.write4ByteTxRx(port, 2, 116, 5000) == (COMM_SUCCESS, 6)
    found, res = ph.broadcastPing(port)
    assert res == COMM_SUCCESS and sorted(found) == [1, 2, 3, 4] and found[4] == [1020, 45]


def test_signed_registers_come_back_unsigned_from_the_sdk(sdk):
    bus, port, ph = sdk
    assert ph.write1ByteTxRx(port, 1, 11, 4)[0] == COMM_SUCCESS  # extended position mode
    bus.servos[1].set_position(-300)
    raw, res, _ = ph.read4ByteTxRx(port, 1, 132)
    assert res == COMM_SUCCESS and raw == 2**32 - 300


def test_sync_read_sync_write_and_motion(sdk):
    bus, port, ph = sdk
    for i in (1, 2, 3, 4):
        assert ph.write1ByteTxRx(port, i, 64, 1) == (COMM_SUCCESS, 0)
    sw = GroupSyncWrite(port, ph, 116, 4)
    goals = {1: 1000, 2: 3000, 3: 2048, 4: 2100}
    for i, g in goals.items():
        sw.addParam(i, list(g.to_bytes(4, "little")))
    assert sw.txPacket() == COMM_SUCCESS
    sr = GroupSyncRead(port, ph, 122, 14)  # moving .. present position
    for i in goals:
        sr.addParam(i)
    done = threading.Event()
    for _ in range(2000):  # poll the bus until every servo reports in position
        assert sr.txRxPacket() == COMM_SUCCESS
        if all(sr.getData(i, 122, 1) == 0 and sr.getData(i, 132, 4) == g for i, g in goals.items()):
            done.set()
            break
        done.wait(0.002)
    assert done.is_set()
    assert sr.getData(2, 123, 1) & 1  # Moving Status: in position


def test_bulk_read_and_bulk_write(sdk):
    bus, port, ph = sdk
    bw = GroupBulkWrite(port, ph)
    assert bw.addParam(1, 112, 4, [10, 0, 0, 0]) and bw.addParam(2, 65, 1, [1])
    assert bw.txPacket() == COMM_SUCCESS
    br = GroupBulkRead(port, ph)
    assert br.addParam(1, 112, 4) and br.addParam(2, 65, 1) and br.addParam(3, 144, 2)
    assert br.txRxPacket() == COMM_SUCCESS
    assert br.getData(1, 112, 4) == 10
    assert br.getData(2, 65, 1) == 1
    assert br.getData(3, 144, 2) == 120  # 12.0 V


def test_one_silent_servo_times_the_whole_group_out(sdk):
    bus, port, ph = sdk
    bus.servos[3].silent = True
    sr = GroupSyncRead(port, ph, 132, 4)
    for i in (1, 2, 3, 4):
        sr.addParam(i)
    assert sr.txRxPacket() == COMM_RX_TIMEOUT


def test_profile_motion_follows_the_trapezoid(sdk):
    """Timing of a profiled move on the bus agrees with the manual's units (closed form)."""
    bus, port, ph = sdk
    s = bus.servos[1]
    v_reg, a_reg = 20, 10  # 4.58 rpm, 2145.77 rev/min^2
    ph.write4ByteTxRx(port, 1, 112, v_reg)
    ph.write4ByteTxRx(port, 1, 108, a_reg)
    ph.write4ByteTxRx(port, 1, 116, 2048)  # goal = present before torque on: no jump
    ph.write1ByteTxRx(port, 1, 64, 1)
    v = v_reg * 0.229 * 4096 / 60
    a = a_reg * 214.577 * 4096 / 3600
    d = 1000
    total = d / v + v / a
    t0 = s.clock()
    ph.write4ByteTxRx(port, 1, 116, 2048 + d)
    t1 = s.clock()
    # the move starts when the write arrives (between the two clock readings, however
    # long a loaded machine takes over the round trip: at 50x a 3 ms trip is 0.15 s);
    # sample the model at fixed servo times (its clock is the bus's scaled clock)
    seg = s._seg
    assert seg is not None and t0 <= seg.t0 <= t1
    for frac in (0.1, 0.5, 0.9):
        t = frac * total
        pos, _, moving = s._position_at(seg.t0 + t)
        ramp = v / a
        if t < ramp:
            expect = 0.5 * a * t * t
        elif t > total - ramp:
            expect = d - 0.5 * a * (total - t) ** 2
        else:
            expect = 0.5 * a * ramp**2 + v * (t - ramp)
        assert pos - 2048 == pytest.approx(expect, rel=1e-9)
        assert moving
    assert not s._position_at(seg.t0 + total * 1.001)[2]
    assert math.isclose(s._position_at(seg.t0 + total * 1.001)[0], 2048 + d)


def test_status_return_level_and_delayed_replies(sdk):
    bus, port, ph = sdk
    assert ph.write1ByteTxRx(port, 2, 68, 0) == (COMM_SUCCESS, 0)  # the ack still comes (level 2)
    assert ph.ping(port, 2)[1] == COMM_SUCCESS  # PING always answers
    assert ph.read1ByteTxRx(port, 2, 68)[1] == COMM_RX_TIMEOUT  # level 0: READ does not
    bus.delay_rate, bus.delay_s = 1.0, 0.005  # below the SDK's 34 ms timeout: late but fine
    assert ph.read1ByteTxRx(port, 1, 68) == (2, COMM_SUCCESS, 0)
    assert bus.stats.delayed >= 1


def test_current_and_temperature_follow_load(sdk):
    bus, port, ph = sdk
    s = bus.servos[1]
    assert s.get("present_current") == 0  # torque off: no current
    ph.write4ByteTxRx(port, 1, 116, 2048)
    ph.write1ByteTxRx(port, 1, 64, 1)
    holding = s.get("present_current")
    ph.write4ByteTxRx(port, 1, 112, 1)  # crawl: the move lasts long in servo time
    ph.write4ByteTxRx(port, 1, 116, 4000)
    moving = abs(s.get("present_current"))
    assert moving > holding > 0
    t0, temp0 = s.clock(), s.get("present_temperature")
    done = threading.Event()
    while s.clock() - t0 < 60.0 and not done.wait(0.01):  # one heating time constant
        pass
    assert s.get("present_temperature") > temp0 + 5


def test_overheating_trips_at_the_temperature_limit(sdk):
    bus, port, ph = sdk
    s = bus.servos[1]
    assert ph.write1ByteTxRx(port, 1, 31, 36) == (COMM_SUCCESS, 0)  # Temperature Limit 36 degC
    ph.write4ByteTxRx(port, 1, 116, 2048)
    ph.write1ByteTxRx(port, 1, 64, 1)
    ph.write4ByteTxRx(port, 1, 112, 1)
    ph.write4ByteTxRx(port, 1, 116, 4000)  # a long, loaded move heats the motor
    t0, wait = s.clock(), threading.Event()
    while s.clock() - t0 < 60.0 and not wait.wait(0.01):
        pass
    value, res, err = ph.read1ByteTxRx(port, 1, 70)
    assert res == COMM_SUCCESS and value == 0x04 and err & 0x80  # overheating, alert bit
    assert ph.read1ByteTxRx(port, 1, 64)[0] == 0  # shutdown cut torque
    assert ph.write1ByteTxRx(port, 1, 64, 1)[1] & 0x7F == 7  # refused until REBOOT
    assert ph.reboot(port, 1)[0] == COMM_SUCCESS
    assert ph.read1ByteTxRx(port, 1, 70)[0] == 0x04  # still too hot: trips again at once
    assert ph.write1ByteTxRx(port, 1, 31, 80) == (COMM_SUCCESS, 0x80)  # EEPROM: torque is off
    assert ph.reboot(port, 1)[0] == COMM_SUCCESS
    assert ph.read1ByteTxRx(port, 1, 70) == (0, COMM_SUCCESS, 0)
