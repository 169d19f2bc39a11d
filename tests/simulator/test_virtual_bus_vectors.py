"""The e-manual's test vectors, sent as raw bytes over the pty, get the manual's replies."""

from __future__ import annotations

import serial

from gonio.rig.protocol import Framer
from gonio.simulator.servo_model import VirtualServo
from gonio.simulator.virtual_bus import VirtualBus


def h(s: str) -> bytes:
    return bytes.fromhex(s)


def exchange(bus: VirtualBus, request: bytes, n_replies: int, chunks: int = 1) -> list[bytes]:
    """Send ``request`` (optionally in fragments) and collect ``n_replies`` whole packets."""
    with serial.Serial(bus.port, 1_000_000, timeout=1.0) as ser:
        step = max(1, len(request) // chunks)
        for k in range(0, len(request), step):
            ser.write(request[k : k + step])
            ser.flush()
        framer, out = Framer(), []
        while len(out) < n_replies:
            data = ser.read(1)
            assert data, f"timed out after {len(out)} of {n_replies} replies"
            data += ser.read(ser.in_waiting)
            out += [pk.raw for pk in framer.feed(data)]
        return out


def manual_bus(**kw) -> VirtualBus:
    # The manual's examples come from an XM430-W210 (model 1030) on firmware 38.
    return VirtualBus([VirtualServo(1, "XM430-W210", 38), VirtualServo(2, "XM430-W210", 38)], **kw)


def test_ping_and_broadcast_ping():
    with manual_bus() as bus:
        assert exchange(bus, h("FF FF FD 00 01 03 00 01 19 4E"), 1) == [
            h("FF FF FD 00 01 07 00 55 00 06 04 26 65 5D")
        ]
        replies = exchange(bus, h("FF FF FD 00 FE 03 00 01 31 42"), 2)
        assert replies[1] == h("FF FF FD 00 02 07 00 55 00 06 04 26 6F 6D")


def test_read_present_position_fragmented_with_garbage():
    with manual_bus() as bus:
        bus.servos[1].set_position(166)
        req = h("00 FF 13 FF FF FD 00 01 07 00 02 84 00 04 00 1D 15")  # leading garbage
        assert exchange(bus, req, 1, chunks=len(req)) == [
            h("FF FF FD 00 01 08 00 55 00 A6 00 00 00 8C C0")
        ]


def test_write_and_ack_then_goal_is_stored():
    with manual_bus() as bus:
        assert exchange(bus, h("FF FF FD 00 01 09 00 03 74 00 00 02 00 00 CA 89"), 1) == [
            h("FF FF FD 00 01 04 00 55 00 A1 0C")
        ]
        assert bus.servos[1].get("goal_position") == 512


def test_reg_write_action_factory_reset_reboot_clear():
    ack = h("FF FF FD 00 01 04 00 55 00 A1 0C")
    with manual_bus() as bus:
        s = bus.servos[1]
        assert exchange(bus, h("FF FF FD 00 01 09 00 04 68 00 C8 00 00 00 AE 8E"), 1) == [ack]
        assert s.get("goal_velocity") == 0 and s.get("registered_instruction") == 1
        assert exchange(bus, h("FF FF FD 00 01 03 00 05 02 CE"), 1) == [ack]
        assert s.get("goal_velocity") == 200
        assert exchange(bus, h("FF FF FD 00 01 04 00 06 01 A1 E6"), 1) == [ack]
        assert s.get("goal_velocity") == 0 and s.get("id") == 1
        assert exchange(bus, h("FF FF FD 00 01 03 00 08 2F 4E"), 1) == [ack]
        s.set_position(4096 * 3 + 100)
        assert exchange(bus, h("FF FF FD 00 01 08 00 10 01 44 58 4C 22 B1 DC"), 1) == [ack]
        assert s.get("present_position") == 100


def test_sync_read_and_sync_write():
    with manual_bus() as bus:
        bus.servos[2].set_position(2079)
        replies = exchange(bus, h("FF FF FD 00 FE 09 00 82 84 00 04 00 01 02 CE FA"), 2)
        assert replies[1] == h("FF FF FD 00 02 08 00 55 00 1F 08 00 00 BA BE")
        with serial.Serial(bus.port, 1_000_000, timeout=0.2) as ser:
            ser.write(h("FF FF FD 00 FE 11 00 83 74 00 04 00 01 96 00 00 00 02 AA 00 00 00 82 87"))
            assert ser.read(1) == b""  # sync write never answers
        assert bus.servos[1].get("goal_position") == 150
        assert bus.servos[2].get("goal_position") == 170


def test_bulk_read_and_bulk_write():
    with manual_bus() as bus:
        bus.servos[1].voltage_raw = 119
        bus.servos[2].set_temperature(36.0)  # 30 degC ambient + 6
        replies = exchange(bus, h("FF FF FD 00 FE 0D 00 92 01 90 00 02 00 02 92 00 01 00 1A 05"), 2)
        assert replies == [
            h("FF FF FD 00 01 06 00 55 00 77 00 C3 69"),
            h("FF FF FD 00 02 05 00 55 00 24 8B A9"),
        ]
        bus.servos[1].set_u("max_voltage_limit", 150)
        bus.servos[2].set_u("temperature_limit", 70)
        with serial.Serial(bus.port, 1_000_000, timeout=0.2) as ser:
            ser.write(h("FF FF FD 00 FE 10 00 93 01 20 00 02 00 A0 00 02 1F 00 01 00 50 B7 68"))
            assert ser.read(1) == b""
        assert bus.servos[1].get("max_voltage_limit") == 160
        assert bus.servos[2].get("temperature_limit") == 80


def test_fast_sync_read():
    with VirtualBus([3, 7, 4], firmware=46) as bus:
        for i, pos in ((3, 166), (7, 2079), (4, 1023)):
            bus.servos[i].set_position(pos)
        assert exchange(bus, h("FF FF FD 00 FE 0A 00 8A 84 00 04 00 03 07 04 20 F2"), 1) == [
            h(
                "FF FF FD 00 FE 19 00 55 00 03 A6 00 00 00 84 08 00 07 1F 08 00 00 16 CA"
                " 00 04 FF 03 00 00 D1 9E"
            )
        ]


def test_computed_vectors_torque_access_error_alert_and_stuffing():
    with manual_bus() as bus:
        ack = h("FF FF FD 00 01 04 00 55 00 A1 0C")
        assert exchange(bus, h("FF FF FD 00 01 06 00 03 40 00 01 DB 66"), 1) == [ack]
        assert bus.servos[1].get("torque_enable") == 1
        # EEPROM (ID, address 7) is locked while torque is on -> access error
        req = h("FF FF FD 00 01 06 00 03 07 00 05")
        from gonio.rig.protocol import crc16

        c = crc16(req)
        req += bytes([c & 0xFF, c >> 8])
        assert exchange(bus, req, 1) == [h("FF FF FD 00 01 04 00 55 07 B0 8C")]
        # a hardware error sets the alert bit on every reply and cuts torque
        bus.servos[1].inject_fault(0x20)
        assert bus.servos[1].get("torque_enable") == 0
        assert exchange(bus, h("FF FF FD 00 01 09 00 03 74 00 00 02 00 00 CA 89"), 1) == [
            h("FF FF FD 00 01 04 00 55 80 A2 8F")
        ]
        assert exchange(bus, h("FF FF FD 00 01 03 00 08 2F 4E"), 1)  # REBOOT clears it
        assert bus.servos[1].get("hardware_error_status") == 0
    with manual_bus() as bus:
        assert exchange(bus, h("FF FF FD 00 01 0A 00 03 E0 00 FF FF FD FD FD 6F 78"), 1) == [
            h("FF FF FD 00 01 04 00 55 00 A1 0C")
        ]
        assert bytes(bus.servos[1].mem[224:228]) == h("FF FF FD FD")
        # the reply to a read of it is stuffed too
        from gonio.rig.protocol import build_packet, build_status

        assert exchange(bus, build_packet(1, 0x02, h("E0 00 04 00")), 1) == [
            build_status(1, 0, h("FF FF FD FD"))
        ]
        assert build_status(1, 0, h("FF FF FD FD"))[7:14] == h("55 00 FF FF FD FD FD")


def test_crc_error_gets_crc_error_status():
    with manual_bus() as bus:
        replies = exchange(bus, h("FF FF FD 00 01 03 00 01 19 4F"), 1)
        assert replies[0][8] == 0x03
