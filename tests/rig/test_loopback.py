"""The in-process loopback transport: the real packets, the real servo logic, no pty.

The same cases as the dynamixel-sdk transport's tests (tests/rig/test_transport.py), so
the two implementations of the rig's bus interface are held to one behaviour.
"""

from __future__ import annotations

import logging

import pytest

from gonio.errors import BusError, RigError
from gonio.rig.bus import BusTransport
from gonio.rig.control_table import MODELS
from gonio.rig.transport import Transport
from gonio.simulator.loopback import LoopbackTransport
from gonio.simulator.virtual_bus import ServoBus

REG = MODELS["XM430-W350"].registers


def test_both_transports_are_bus_transports(loopback):
    assert isinstance(loopback, BusTransport)
    assert isinstance(Transport("/dev/null"), BusTransport)
    assert not isinstance(object(), BusTransport)


class RecordingBus(ServoBus):
    """A servo bus that keeps the raw bytes of every instruction packet it executes."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.seen: list[bytes] = []

    def handle(self, pkt):
        self.seen.append(pkt.raw)
        return super().handle(pkt)


def test_packets_on_the_wire_are_the_manuals():
    """The loopback sends what the e-manual shows: its PING of ID 1 reaches the bus as
    ``FF FF FD 00 01 03 00 01 19 4E``, its READ of 4 bytes at 132 as in the manual's
    READ example, and the replies are parsed from bytes."""
    bus = RecordingBus([1])
    bus.servos[1].set_position(166)
    with LoopbackTransport(bus) as t:
        assert t.ping(1) == (1020, 45)
        assert t.read(1, REG["present_position"]) == 166
    assert bus.seen == [
        bytes.fromhex("FF FF FD 00 01 03 00 01 19 4E"),
        bytes.fromhex("FF FF FD 00 01 07 00 02 84 00 04 00 1D 15"),
    ]


def test_stuffed_payload_round_trips(loopback, servo_bus):
    value = bytes.fromhex("FF FF FD FD")
    with loopback:
        loopback.write_bytes(1, 224, value)
        assert bytes(servo_bus.servos[1].mem[224:228]) == value
        assert loopback.read_bytes(1, 224, 4) == value  # the stuffed reply is unstuffed
        assert loopback.counters["stuffed"] == 1


def test_signed_conversions(loopback, servo_bus):
    with loopback:
        loopback.write(1, REG["operating_mode"], 4)
        servo_bus.servos[1].set_position(-1234)
        assert loopback.read(1, REG["present_position"]) == -1234
        loopback.write(2, REG["homing_offset"], -500)
        assert loopback.read(2, REG["homing_offset"]) == -500
        with pytest.raises(RigError, match="read-only"):
            loopback.write(1, REG["present_position"], 3)


def test_device_errors_are_raised_not_retried(loopback):
    with loopback:
        loopback.write(1, REG["torque_enable"], 1)
        with pytest.raises(
            BusError, match="servo 1 refused WRITE operating_mode=4: access error"
        ) as info:
            loopback.write(1, REG["operating_mode"], 4)
        assert (info.value.servo, info.value.cause) == (1, "device_error")
        assert loopback.counters["retries"] == 0


def test_silent_servo_raises_bus_error_naming_it(loopback, servo_bus):
    servo_bus.servos[2].silent = True
    with loopback:
        with pytest.raises(BusError, match="servo 2 did not answer READ .* after 4 attempts") as e:
            loopback.read(2, REG["present_position"])
        assert (e.value.servo, e.value.cause) == (2, "timeout")
        with pytest.raises(BusError) as e:
            loopback.sync_read([1, 2, 3], 132, 4)
        assert (e.value.servo, e.value.cause) == (2, "timeout")
        assert loopback.ping(2) is None and loopback.ping(1) == (1020, 45)


def test_lossy_bus_retries_are_counted_and_logged(caplog):
    caplog.set_level(logging.INFO, logger="gonio.rig.bus")
    bus = ServoBus([1, 2], fault_rate=0.2, seed=3)
    bus.servos[2].set_position(777)
    with LoopbackTransport(bus, retries=8) as t:
        for _ in range(200):
            assert t.read(2, REG["present_position"]) == 777
        faults = bus.stats.corrupted + bus.stats.dropped
        retries = [r for r in caplog.records if r.getMessage().startswith("retry ")]
        assert faults > 20
        # no clock, no load, one reply per attempt: every fault costs exactly one retry
        assert t.counters["retries"] == len(retries) == faults
        for _ in range(100):  # a group read is retried whole, whichever reply was lost
            assert t.sync_read([1, 2], 132, 4)[2] == (777).to_bytes(4, "little")
    assert bus.stats.corrupted + bus.stats.dropped > faults + 10


def test_a_broadcast_reaches_every_servo_and_gets_no_reply(loopback, servo_bus):
    with loopback:
        for i in (1, 2, 3, 4):
            loopback.write(i, REG["torque_enable"], 1)
        loopback.broadcast_write(REG["torque_enable"], 0)
    assert servo_bus.torque() == {1: 0, 2: 0, 3: 0, 4: 0}
    assert servo_bus.stats.replies == 4 + 0  # the four WRITEs' replies, none for the broadcast


def test_closed_loopback_refuses(loopback):
    with pytest.raises(BusError, match="not open") as info:
        loopback.read(1, REG["model_number"])
    assert info.value.cause == "port"


def test_the_loopback_needs_only_the_rigs_protocol_definitions():
    """The simulator may import gonio.rig.protocol and control_table, never the rig's
    transport, device or kinematics (nor dynamixel-sdk): checked in a fresh interpreter."""
    import subprocess
    import sys

    code = (
        "import sys, gonio.simulator.loopback\n"
        "bad = sorted(m for m in sys.modules if m in ('gonio.rig.transport', 'gonio.rig.device',"
        " 'gonio.rig.kinematics', 'gonio.rig.servo', 'dynamixel_sdk'))\n"
        "print(bad)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
