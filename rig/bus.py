"""What the rig needs from a servo bus: the :class:`BusTransport` protocol.

:class:`gonio.rig.device.Rig` and :class:`gonio.rig.servo.Servo` talk to the servos only
through these methods, so the bus is injected: the dynamixel-sdk
:class:`gonio.rig.transport.Transport` on a serial port (a U2D2, or the simulator's pty),
or the simulator's in-process :class:`~gonio.simulator.loopback.LoopbackTransport` for fast
tests.  Implementations match it by structure (they need not import it).

Failures: a servo that does not answer (or answers garbage) after every retry raises
:class:`~gonio.errors.BusError` with ``servo`` and ``cause`` (``"timeout"``,
``"corrupt"``, ``"port"``); a servo that answers with an error code in its status packet
raises ``BusError(cause="device_error")``.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Mapping
from typing import Protocol, runtime_checkable

from gonio.rig.control_table import Register

__all__ = ["BusTransport"]


@runtime_checkable
class BusTransport(Protocol):
    """A Dynamixel Protocol 2.0 bus with retries.

    Attributes
    ----------
    port_name
        Where the bus is (a device path, or a name for an in-process bus).
    baud_rate
        Bits per second.
    counters
        ``"transactions"``, ``"retries"``, ``"timeouts"``, ``"corrupt"``, ``"stuffed"``
        (the rig adds ``"goal_resends"``).
    alerts
        IDs whose last status packet had the alert bit set (read register 70).
    """

    port_name: str
    baud_rate: int
    counters: Counter[str]
    alerts: set[int]

    def open(self) -> BusTransport:
        """Open the bus.  Raises RigError (BusError ``cause="port"``) if it cannot."""
        ...

    def close(self) -> None:
        """Close the bus (idempotent)."""
        ...

    @property
    def is_open(self) -> bool: ...

    def reset(self) -> None:
        """Recover after an interrupted transaction (drop half-read input)."""
        ...

    def ping(self, dxl_id: int, retries: int | None = None) -> tuple[int, int] | None:
        """(model number, firmware version) of ``dxl_id``, or None if it does not answer."""
        ...

    def read_bytes(self, dxl_id: int, address: int, length: int) -> bytes:
        """READ ``length`` raw bytes from ``address``."""
        ...

    def read(self, dxl_id: int, reg: Register) -> int:
        """Read a register; signed registers come back signed."""
        ...

    def write_bytes(self, dxl_id: int, address: int, data: bytes, what: str = "") -> None:
        """WRITE raw bytes and check the status packet."""
        ...

    def write(self, dxl_id: int, reg: Register, value: int) -> None:
        """Write a register value (RigError for a read-only register)."""
        ...

    def sync_read(self, ids: Iterable[int], address: int, length: int) -> dict[int, bytes]:
        """SYNC_READ ``length`` bytes at ``address`` from every ID; all or nothing."""
        ...

    def sync_write(self, reg: Register, values: Mapping[int, int]) -> None:
        """SYNC_WRITE one register to several servos (no reply)."""
        ...

    def broadcast_write(self, reg: Register, value: int) -> None:
        """WRITE to the broadcast ID (no reply): emergency torque off."""
        ...

    def reboot(self, dxl_id: int) -> None:
        """REBOOT a servo (clears a hardware error; torque comes back off)."""
        ...
