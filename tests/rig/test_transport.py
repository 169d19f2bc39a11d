"""Transport: stuffing workaround, signed values, retries, timeouts."""

from __future__ import annotations

import logging

import pytest
from dynamixel_sdk import COMM_SUCCESS, PacketHandler

from gonio.errors import BusError, RigError
from gonio.rig.control_table import MODELS
from gonio.rig.protocol import build_packet, crc16, stuff, unstuff
from gonio.rig.transport import Transport
from gonio.simulator.virtual_bus import VirtualBus

REG = MODELS["XM430-W350"].registers


def test_protocol_helpers_against_manual():
    assert build_packet(1, 0x01) == bytes.fromhex("FF FF FD 00 01 03 00 01 19 4E")
    assert crc16(bytes.fromhex("FF FF FD 00 01 03 00 01")) == 0x4E19
    assert unstuff(stuff(b"\xff\xff\xfd\xff\xff\xfd")) == b"\xff\xff\xfd\xff\xff\xfd"


def test_stuffing_workaround(vbus):
    value = bytes.fromhex("FF FF FD FD")
    # the bare SDK sends the payload unstuffed: the servo sees a different packet
    with Transport(vbus.port) as bus:
        ph = PacketHandler(2.0)
        res, err = ph.writeTxRx(bus._port, 1, 224, 4, list(value))
        assert (res, err) != (COMM_SUCCESS, 0) or bytes(vbus.servos[1].mem[224:228]) != value
        vbus.servos[1].mem[224:228] = bytes(4)
        bus.write_bytes(1, 224, value)
        assert bytes(vbus.servos[1].mem[224:228]) == value
        assert bus.read_bytes(1, 224, 4) == value  # the stuffed reply is unstuffed
        assert bus.counters["stuffed"] == 1


def test_signed_conversions(vbus):
    with Transport(vbus.port) as bus:
        bus.write(1, REG["operating_mode"], 4)
        vbus.servos[1].set_position(-1234)
        assert bus.read(1, REG["present_position"]) == -1234
        bus.write(2, REG["homing_offset"], -500)
        assert bus.read(2, REG["homing_offset"]) == -500
        with pytest.raises(RigError, match="read-only"):
            bus.write(1, REG["present_position"], 3)


def test_device_errors_are_raised_not_retried(vbus):
    with Transport(vbus.port) as bus:
        bus.write(1, REG["torque_enable"], 1)
        with pytest.raises(
            BusError, match="servo 1 refused WRITE operating_mode=4: access error"
        ) as info:
            bus.write(1, REG["operating_mode"], 4)
        assert (info.value.servo, info.value.cause) == (1, "device_error")
        assert bus.counters["retries"] == 0


def test_replies_are_waited_for_not_polled():
    """The SDK opens the port non-blocking and loops on reads until a reply comes: the
    transport's port waits in select instead (a busy loop holds a core and, with a
    virtual bus served from a thread, the GIL).  Counted, not timed: a polling client
    reads hundreds of times per reply, a waiting one a few (a status may arrive in more
    than one chunk).  No switch-interval fixture: the default interpreter, as the demo."""
    ids = (1, 2, 3, 4)
    with VirtualBus(list(ids), time_scale="virtual", seed=0) as vb:
        with Transport(vb.port, timeout_ms=500) as bus:
            ser = bus._port.ser
            calls = []
            real_read = ser.read

            def counted(n=1):
                calls.append(n)
                return real_read(n)

            ser.read = counted
            for _ in range(20):
                blocks = bus.sync_read(ids, REG["present_position"].address, 4)
                assert sorted(blocks) == list(ids)
            assert bus.read(3, REG["present_position"]) == 2048  # its start position
        # 4 status packets per SYNC_READ (header, then the rest of each): 8 reads if
        # every packet comes whole; a few more where the pty splits one
        assert len(calls) <= 21 * 4 * 4, len(calls)


def test_retries_are_counted_and_logged(gil_handover, caplog):
    from gonio.simulator.virtual_bus import VirtualBus

    caplog.set_level(logging.INFO, logger="gonio.rig.bus")
    with (
        VirtualBus([1, 2], fault_rate=0.2, seed=3) as vb,
        Transport(vb.port, retries=8, timeout_ms=10) as bus,
    ):
        for _ in range(100):
            assert bus.read(2, REG["model_number"]) == 1020
        faults = vb.stats.corrupted + vb.stats.dropped
    retries = [r for r in caplog.records if r.getMessage().startswith("retry ")]
    assert faults > 5
    assert bus.counters["retries"] == len(retries) >= faults  # load may add timeouts


def test_silent_servo_gives_a_clear_error(vbus):
    vbus.servos[2].silent = True
    with Transport(vbus.port, retries=1, timeout_ms=5) as bus:
        with pytest.raises(BusError, match="servo 2 did not answer READ .* after 2 attempts") as e:
            bus.read(2, REG["present_position"])
        assert (e.value.servo, e.value.cause) == (2, "timeout")
        # the healthy servo still answers; the 5 ms timeout is tight on a loaded machine,
        # so it gets retries (a lost firmware read is retried, never reported as 0)
        assert bus.ping(2) is None and bus.ping(1, retries=10) == (1020, 45)
    # a group read names the servo that stayed silent, not the whole group (a timeout
    # generous enough that the healthy servos' replies are never the late ones)
    with Transport(vbus.port, retries=1, timeout_ms=100) as bus:
        with pytest.raises(BusError, match="did not answer SYNC_READ") as e:
            bus.sync_read([1, 2, 3], 132, 4)
        assert (e.value.servo, e.value.cause) == (2, "timeout")


def test_a_late_reply_is_never_taken_for_the_retrys(gil_handover):
    """Protocol 2.0 status packets do not name the instruction they answer: a reply that
    misses its timeout and arrives during the retry must be dropped, not parsed as the
    retry's (a late firmware READ read as a PING gives a model number of garbage)."""
    from gonio.simulator.virtual_bus import VirtualBus

    with (
        VirtualBus([1], delay_rate=0.3, delay_s=0.012, seed=5) as vb,
        Transport(vb.port, retries=30, timeout_ms=6) as bus,
    ):
        vb.servos[1].set_position(1234)
        for _ in range(40):
            assert bus.ping(1) == (1020, 45)
            assert bus.read(1, REG["present_position"]) == 1234
        assert bus.counters["retries"] > 5  # replies did come late


@pytest.mark.parametrize(
    ("failures", "cause", "expected"),
    [
        # the flake seen on a loaded machine: servo 2 silent, its last wait ended with
        # servo 3's reply half-received (the SDK: corrupt)
        ([(1, "T"), (1, "T"), (1, "T"), (1, "C")], "corrupt", (2, "timeout")),
        # the last attempt stopped at servo 1, merely late: the furthest attempt names 2
        ([(1, "T"), (0, "T")], "timeout", (2, "timeout")),
        # a servo that answers garbage every time stays corrupt
        ([(2, "C"), (2, "C")], "corrupt", (3, "corrupt")),
        # nothing could be sent: no servo to name
        ([(None, "C")], "port", (None, "port")),
        ([], "timeout", (None, "timeout")),
    ],
)
def test_sync_read_names_the_servo_every_attempt_points_to(failures, cause, expected):
    from dynamixel_sdk import COMM_RX_CORRUPT, COMM_RX_TIMEOUT

    from gonio.rig.transport import sync_read_culprit

    code = {"T": COMM_RX_TIMEOUT, "C": COMM_RX_CORRUPT}
    got = sync_read_culprit((1, 2, 3, 4), [(k, code[r]) for k, r in failures], cause)
    assert got == expected
