"""Dynamixel Protocol 2.0 packets: CRC, byte stuffing, building and framing.

dynamixel-sdk builds and parses packets inside its PacketHandler, but (4.1.0) never
stuffs what it sends and offers no stand-alone framer; the controller needs a correct
packet builder for its stuffing workaround, and the virtual bus needs a framer that
tolerates garbage and fragments.  Both are hand-written here, small and shared, and
tested against the e-manual's vectors rather than against the SDK.
"""

from __future__ import annotations

from dataclasses import dataclass

from gonio.errors import BusError

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
MAX_PACKET_LEN = 1024  # the SDK's RXPACKET_MAX_LEN; longer LEN fields are garbage

# Instructions
PING = 0x01
READ = 0x02
WRITE = 0x03
REG_WRITE = 0x04
ACTION = 0x05
FACTORY_RESET = 0x06
REBOOT = 0x08
CLEAR = 0x10
STATUS = 0x55
SYNC_READ = 0x82
SYNC_WRITE = 0x83
FAST_SYNC_READ = 0x8A
BULK_READ = 0x92
BULK_WRITE = 0x93
FAST_BULK_READ = 0x9A

# Status ERR byte
ERR_ALERT = 0x80
ERR_RESULT_FAIL = 1
ERR_INSTRUCTION = 2
ERR_CRC = 3
ERR_DATA_RANGE = 4
ERR_DATA_LENGTH = 5
ERR_DATA_LIMIT = 6
ERR_ACCESS = 7
ERR_NAMES = {
    ERR_RESULT_FAIL: "result fail",
    ERR_INSTRUCTION: "instruction error",
    ERR_CRC: "CRC error",
    ERR_DATA_RANGE: "data range error",
    ERR_DATA_LENGTH: "data length error",
    ERR_DATA_LIMIT: "data limit error",
    ERR_ACCESS: "access error",
}


def check_status(what: str, dxl_id: int, error: int) -> None:
    """Raise when a status packet's ERR byte carries an error code (the alert bit aside).

    Parameters
    ----------
    what
        The instruction, for the message (``"WRITE torque_enable=1"``).
    dxl_id
        The servo that answered.
    error
        The status packet's ERR byte.

    Raises
    ------
    BusError
        ``cause="device_error"``: the servo answered and refused the instruction.
    """
    code = error & 0x7F
    if code:
        name = ERR_NAMES.get(code, f"error {code}")
        raise BusError(
            f"servo {dxl_id} refused {what}: {name} (status error 0x{error:02X})",
            servo=dxl_id,
            cause="device_error",
        )


def _crc_table() -> list[int]:
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return table


_CRC_TABLE = _crc_table()


def crc16(data: bytes | bytearray, crc: int = 0) -> int:
    """CRC-16 of Protocol 2.0 (polynomial 0x8005, initial 0, not reflected).

    ``crc`` continues a running CRC (FAST_SYNC_READ replies chain it over devices).
    """
    for b in data:
        crc = ((crc << 8) ^ _CRC_TABLE[((crc >> 8) ^ b) & 0xFF]) & 0xFFFF
    return crc


def stuff(body: bytes) -> bytes:
    """Insert ``FD`` after every ``FF FF FD`` (the body is INST..last parameter)."""
    return body.replace(b"\xff\xff\xfd", b"\xff\xff\xfd\xfd")


def unstuff(body: bytes) -> bytes:
    """Undo :func:`stuff`."""
    return body.replace(b"\xff\xff\xfd\xfd", b"\xff\xff\xfd")


def needs_stuffing(body: bytes) -> bool:
    """Whether INST..params contain ``FF FF FD`` (dynamixel-sdk 4.1.0 would send it raw)."""
    return b"\xff\xff\xfd" in body


def build_packet(dxl_id: int, instruction: int, params: bytes = b"") -> bytes:
    """A complete instruction packet, stuffed, with LEN and CRC computed after stuffing."""
    body = stuff(bytes([instruction]) + bytes(params))
    n = len(body) + 2
    head = HEADER + bytes([dxl_id & 0xFF, n & 0xFF, n >> 8])
    pkt = head + body
    crc = crc16(pkt)
    return pkt + bytes([crc & 0xFF, crc >> 8])


def build_status(dxl_id: int, error: int, params: bytes = b"") -> bytes:
    """A status packet (INST 0x55, then the ERR byte and the parameters)."""
    return build_packet(dxl_id, STATUS, bytes([error]) + bytes(params))


@dataclass(frozen=True)
class Packet:
    """A framed packet.

    Attributes
    ----------
    dxl_id, instruction
        ID and instruction byte.
    params
        Parameters after unstuffing (for a status packet: ERR byte first).
    crc_ok
        Whether the CRC matched.
    raw
        The bytes as received.
    """

    dxl_id: int
    instruction: int
    params: bytes
    crc_ok: bool
    raw: bytes


class Framer:
    """Split a byte stream into packets by header and LEN.

    Leading garbage is skipped; fragments are buffered until the packet is complete;
    ``FF FF FD`` inside a packet never restarts framing (framing goes by LEN).  A LEN
    that is too short or too long is treated as garbage: framing resumes one byte later.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.garbage_bytes = 0

    def feed(self, data: bytes) -> list[Packet]:
        """Add received bytes; return the packets completed by them."""
        self._buf += data
        out: list[Packet] = []
        buf = self._buf
        while True:
            i = buf.find(HEADER)
            if i < 0:
                # keep a possible partial header at the end
                keep = 0
                for k in (3, 2, 1):
                    if len(buf) >= k and HEADER.startswith(bytes(buf[-k:])):
                        keep = k
                        break
                self.garbage_bytes += len(buf) - keep
                del buf[: len(buf) - keep]
                break
            if i:
                self.garbage_bytes += i
                del buf[:i]
            if len(buf) < 7:
                break
            n = buf[5] | (buf[6] << 8)
            if n < 3 or n > MAX_PACKET_LEN:
                self.garbage_bytes += 1
                del buf[:1]
                continue
            total = 7 + n
            if len(buf) < total:
                break
            raw = bytes(buf[:total])
            del buf[:total]
            crc_ok = crc16(raw[:-2]) == (raw[-2] | (raw[-1] << 8))
            body = unstuff(raw[7:-2])
            out.append(Packet(raw[4], body[0] if body else -1, body[1:], crc_ok, raw))
        return out

    def clear(self) -> None:
        """Forget buffered bytes."""
        self._buf.clear()


def le(value: int, size: int) -> bytes:
    """Little-endian unsigned bytes of ``value`` (two's complement for negatives)."""
    return (int(value) & ((1 << (8 * size)) - 1)).to_bytes(size, "little")


def from_le(data: bytes) -> int:
    """Unsigned integer from little-endian bytes."""
    return int.from_bytes(data, "little")
