"""The virtual bus hears a client at the speed the kernel keeps, however it was set.

A client may set 1 Mbps the POSIX way (``tcsetattr`` with ``B1000000``, as pyserial on
Linux does) or with ``termios2``: ``TCSETS2`` with the ``BOTHER`` custom-speed flag and
``c_ospeed = 1000000`` (Rust's serialport crate, pyserial on some platforms).  A real U2D2
answers both; the bus must too, and must still refuse a client at another speed.

The ``struct termios2`` layout and the ioctl numbers are written out here from the Linux
UAPI headers (asm-generic ``termbits.h``, ``ioctls.h``), independently of the bus's code.
"""

from __future__ import annotations

import fcntl
import os
import select
import struct
import sys
import termios
import tty

import pytest

from gonio.rig import protocol as p
from gonio.simulator.virtual_bus import VirtualBus

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="termios2 is Linux's")

# struct termios2 { tcflag_t c_iflag, c_oflag, c_cflag, c_lflag; cc_t c_line;
#                   cc_t c_cc[19]; speed_t c_ispeed, c_ospeed; }  -> 44 bytes
_TERMIOS2 = struct.Struct("=4IB19s2I")
_TCGETS2 = 0x802C542A  # _IOR('T', 0x2A, struct termios2)
_TCSETS2 = 0x402C542B  # _IOW('T', 0x2B, struct termios2)
_CBAUD = 0o010017
_BOTHER = 0o010000
_IBSHIFT = 16

PING_1 = bytes.fromhex("FF FF FD 00 01 03 00 01 19 4E")  # e-manual's PING of ID 1


def _set_speed_termios2(fd: int, speed: int) -> None:
    iflag, oflag, cflag, lflag, line, cc, _, _ = _TERMIOS2.unpack(
        fcntl.ioctl(fd, _TCGETS2, bytes(_TERMIOS2.size))
    )
    cflag &= ~(_CBAUD | (_CBAUD << _IBSHIFT))  # input speed follows the output speed
    cflag |= _BOTHER
    fcntl.ioctl(fd, _TCSETS2, _TERMIOS2.pack(iflag, oflag, cflag, lflag, line, cc, speed, speed))


def _ping(fd: int) -> bytes:
    """Send the manual's PING of ID 1; return what comes back within 2 s."""
    os.write(fd, PING_1)
    got = b""
    while len(got) < 14:
        ready, _, _ = select.select([fd], [], [], 2.0)
        if not ready:
            break
        got += os.read(fd, 64)
    return got


@pytest.fixture
def client():
    with VirtualBus([1], seed=0) as bus:
        fd = os.open(bus.port, os.O_RDWR | os.O_NOCTTY)
        try:
            tty.setraw(fd)
            yield bus, fd
        finally:
            os.close(fd)


def test_client_setting_1mbps_through_termios2_bother_is_answered(client):
    bus, fd = client
    _set_speed_termios2(fd, 1_000_000)
    # the POSIX view no longer shows B1000000: that is what fooled the bus
    assert termios.tcgetattr(fd)[4] != termios.B1000000
    reply = _ping(fd)
    # the e-manual's PING status of an XM430-W350 (model 1020 = 0x03FC), firmware 45
    assert reply == p.build_status(1, 0, bytes([0xFC, 0x03, 45]))
    assert bus.stats.wrong_baud == 0


def _unheard(bus: VirtualBus, fd: int) -> bytes:
    """Send the PING, wait (with a deadline) until the bus has counted it as heard at the
    wrong speed, and return whatever came back meanwhile (nothing, if refused)."""
    os.write(fd, PING_1)
    got = b""
    for _ in range(500):
        if bus.stats.wrong_baud:
            break
        if select.select([fd], [], [], 0.01)[0]:
            got += os.read(fd, 64)
    assert bus.stats.wrong_baud == 1
    if select.select([fd], [], [], 0.05)[0]:
        got += os.read(fd, 64)
    return got


def test_client_at_another_speed_is_still_not_heard(client):
    bus, fd = client
    attrs = termios.tcgetattr(fd)
    attrs[4] = attrs[5] = termios.B57600
    termios.tcsetattr(fd, termios.TCSANOW, attrs)
    assert _unheard(bus, fd) == b""


def test_client_at_another_speed_through_termios2_is_not_heard(client):
    bus, fd = client
    _set_speed_termios2(fd, 57_600)
    assert _unheard(bus, fd) == b""
