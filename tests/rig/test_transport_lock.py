"""One controller per serial bus: a second process (or a second Transport) opening the
port the first holds is refused before it sends anything (two `gonio rig move` on one
bus interleaved their packets; one moved the arms, the other failed mid-command).

The port is a real pseudo-terminal (the virtual bus's kind of device), opened by the
real dynamixel-sdk PortHandler; only the bus behind it is absent (nothing is sent)."""

from __future__ import annotations

import os

import pytest

from gonio.errors import BusError
from gonio.rig.transport import Transport


def test_a_held_port_is_refused_and_free_again_when_closed():
    master, slave = os.openpty()
    try:
        name = os.ttyname(slave)
        first = Transport(name).open()
        try:
            with pytest.raises(BusError, match="in use by another process") as exc:
                Transport(name).open()
            assert exc.value.cause == "port" and name in str(exc.value)
        finally:
            first.close()
        again = Transport(name).open()  # closed: the lock went with it
        again.close()
    finally:
        os.close(master)
        os.close(slave)
