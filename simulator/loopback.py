"""An in-process servo bus: the rig's transport over virtual servos, without a pty or thread.

:class:`LoopbackTransport` has the methods of :class:`gonio.rig.bus.BusTransport` (it
matches it by structure; the simulator does not import the rig's transport).  Each call
builds the real Protocol 2.0 instruction packet with :mod:`gonio.rig.protocol`, frames it
as a servo would (:class:`~gonio.rig.protocol.Framer`), hands it to
:meth:`ServoBus.handle <gonio.simulator.virtual_bus.ServoBus.handle>` (the same packet
logic the pty server runs), passes the status packets through the bus's faults
(:meth:`~gonio.simulator.virtual_bus.ServoBus.deliver`) and parses them back with the same
framer: the bytes on the wire are exercised, only the wire is missing.  A reply that
does not come (a silent servo, a dropped packet) is a timeout at once; there is no
clock between request and reply, so the bus's reply delays have no effect here.

The servos' motion follows the bus's clock, as on the pty: the wall clock ``time_scale``
times faster, or with ``time_scale="virtual"`` a virtual clock that a poll of a moving
servo brings to the end of its move (:mod:`gonio.simulator.servo_clock`), so a rig
test's moves take no wall time.

Example
-------
>>> t = LoopbackTransport([1, 2, 3, 4], time_scale="virtual")      # doctest: +SKIP
>>> rig = Rig(config, transport=t)                                  # doctest: +SKIP
"""

from __future__ import annotations

import logging
import threading
from collections import Counter
from collections.abc import Iterable, Mapping
from typing import Any

from gonio.errors import BusError, RigError
from gonio.rig import protocol as p
from gonio.rig.control_table import Register
from gonio.simulator.servo_model import VirtualServo
from gonio.simulator.virtual_bus import ServoBus

__all__ = ["LoopbackTransport"]

log = logging.getLogger("gonio.rig.bus")


class LoopbackTransport:
    """A bus transport that calls a :class:`ServoBus` directly.

    Parameters
    ----------
    bus
        The virtual bus, or IDs / :class:`VirtualServo` objects to build one from (with
        ``bus_options``: ``fault_rate``, ``seed``, ``time_scale``, ...).
    retries
        Extra attempts after a missing or corrupt reply (as the real transport).
    port_name
        Name reported as the port.
    baud_rate
        Reported baud rate (nothing is timed by it).

    Attributes
    ----------
    bus
        The :class:`ServoBus` (for tests: its servos, stats, fault injection).
    counters
        ``Counter`` of ``"transactions"``, ``"retries"``, ``"timeouts"``, ``"corrupt"``,
        ``"stuffed"``.
    alerts
        IDs whose last status packet had the alert bit.
    """

    def __init__(
        self,
        bus: ServoBus | Iterable[int | VirtualServo],
        *,
        retries: int = 3,
        port_name: str = "loopback",
        baud_rate: int = 1_000_000,
        **bus_options: Any,
    ) -> None:
        if isinstance(bus, ServoBus):
            if bus_options:
                raise TypeError(f"bus options {sorted(bus_options)} given with a ready ServoBus")
            self.bus = bus
        else:
            self.bus = ServoBus(bus, **bus_options)
        self.retries = retries
        self.port_name = port_name
        self.baud_rate = baud_rate
        self.lock = threading.RLock()
        self.counters: Counter[str] = Counter()
        self.alerts: set[int] = set()
        self._open = False
        self._to_servos = p.Framer()
        self._from_servos = p.Framer()

    def clock(self) -> float:
        """The servos' clock (s), for timing moves in servo time."""
        return self.bus.clock()

    def sleep(self, seconds: float) -> None:
        """Let ``seconds`` of servo time pass (see :meth:`ServoBus.sleep`)."""
        self.bus.sleep(seconds)

    # ------------------------------------------------------------- lifecycle
    def open(self) -> LoopbackTransport:
        """Connect to the bus (nothing can fail: there is no port)."""
        self._open = True
        return self

    def close(self) -> None:
        """Disconnect (idempotent)."""
        self._open = False

    @property
    def is_open(self) -> bool:
        return self._open

    def __enter__(self) -> LoopbackTransport:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def reset(self) -> None:
        """Forget half-framed bytes on both sides."""
        with self.lock:
            self._to_servos.clear()
            self._from_servos.clear()

    # ------------------------------------------------------------- the wire
    def _exchange(self, packet: bytes) -> list[p.Packet]:
        """Send one instruction packet; return the status packets that come back."""
        if not self._open:
            raise BusError(f"loopback bus {self.port_name!r} is not open", cause="port")
        self._from_servos.clear()  # as a port is cleared before each instruction
        replies: list[bytes] = []
        for pkt in self._to_servos.feed(packet):
            replies += self.bus.handle(pkt)
        delivered, _ = self.bus.deliver(replies)
        return self._from_servos.feed(b"".join(delivered))

    def _send(self, packet: bytes) -> None:
        """An instruction without a reply (broadcast, SYNC_WRITE)."""
        self.counters["transactions"] += 1
        self._exchange(packet)

    def _transact(self, what: str, dxl_id: int, packet: bytes, n_params: int) -> tuple[bytes, int]:
        """Send ``packet`` to ``dxl_id`` with retries; return (parameters, ERR byte).

        The reply must come from ``dxl_id`` with this instruction's parameter count (a
        status packet does not say which instruction it answers) and a good CRC.
        """
        last, cause = "no reply", "timeout"
        for attempt in range(self.retries + 1):
            self.counters["transactions"] += 1
            status = [
                s
                for s in self._exchange(packet)
                if s.dxl_id == dxl_id
                and s.instruction == p.STATUS
                and len(s.params) == 1 + n_params
            ]
            if not status:
                last, cause = "[TxRxResult] There is no status packet!", "timeout"
                self.counters["timeouts"] += 1
            elif not status[0].crc_ok or (status[0].params[0] & 0x7F) == p.ERR_CRC:
                last, cause = "CRC error", "corrupt"
                self.counters["corrupt"] += 1
            else:
                if attempt:
                    log.info("%s on servo %s succeeded after %d retries", what, dxl_id, attempt)
                reply = status[0]
                return bytes(reply.params[1:]), reply.params[0]
            if attempt < self.retries:
                self.counters["retries"] += 1
                level = logging.INFO if what == "PING" else logging.WARNING
                msg = "retry %d/%d of %s on servo %s: %s"
                log.log(level, msg, attempt + 1, self.retries, what, dxl_id, last)
        raise BusError(
            f"servo {dxl_id} did not answer {what} after {self.retries + 1} attempts "
            f"({last}); check the port, baud rate ({self.baud_rate}), ID and power",
            servo=dxl_id,
            cause=cause,
        )

    def _status(self, what: str, dxl_id: int, error: int) -> None:
        if error & p.ERR_ALERT:
            self.alerts.add(dxl_id)
        p.check_status(what, dxl_id, error)

    # ------------------------------------------------------------- instructions
    def ping(self, dxl_id: int, retries: int | None = None) -> tuple[int, int] | None:
        """(model number, firmware version) of ``dxl_id``, or None if it does not answer."""
        with self.lock:
            saved = self.retries
            if retries is not None:
                self.retries = retries
            try:
                data, err = self._transact("PING", dxl_id, p.build_packet(dxl_id, p.PING), 3)
            except BusError:
                return None
            finally:
                self.retries = saved
            if err & p.ERR_ALERT:
                self.alerts.add(dxl_id)
            return p.from_le(data[:2]), data[2]

    def read_bytes(self, dxl_id: int, address: int, length: int) -> bytes:
        """READ ``length`` raw bytes from ``address``."""
        with self.lock:
            packet = p.build_packet(dxl_id, p.READ, p.le(address, 2) + p.le(length, 2))
            data, err = self._transact(f"READ {address}+{length}", dxl_id, packet, length)
            self._status(f"READ {address}", dxl_id, err)
            return data

    def read(self, dxl_id: int, reg: Register) -> int:
        """Read a register; signed registers come back signed."""
        return reg.to_signed(p.from_le(self.read_bytes(dxl_id, reg.address, reg.size)))

    def write_bytes(self, dxl_id: int, address: int, data: bytes, what: str = "") -> None:
        """WRITE raw bytes (stuffed by the packet builder) and check the status packet."""
        what = what or f"WRITE {address}"
        with self.lock:
            params = p.le(address, 2) + bytes(data)
            if p.needs_stuffing(bytes([p.WRITE]) + params):
                self.counters["stuffed"] += 1
            _, err = self._transact(what, dxl_id, p.build_packet(dxl_id, p.WRITE, params), 0)
            self._status(what, dxl_id, err)

    def write(self, dxl_id: int, reg: Register, value: int) -> None:
        """Write a register value (signed values are encoded as two's complement)."""
        if reg.access != "RW":
            raise RigError(f"register {reg.name} is read-only")
        self.write_bytes(
            dxl_id, reg.address, p.le(reg.to_raw(value), reg.size), f"WRITE {reg.name}={value}"
        )

    def sync_read(self, ids: Iterable[int], address: int, length: int) -> dict[int, bytes]:
        """SYNC_READ ``length`` bytes at ``address`` from every ID; all or nothing.

        As with dynamixel-sdk's group read, the status ERR bytes are not looked at (read
        register 70 in the block).
        """
        ids = tuple(ids)
        what = f"SYNC_READ {address}+{length}"
        packet = p.build_packet(
            p.BROADCAST_ID, p.SYNC_READ, p.le(address, 2) + p.le(length, 2) + bytes(ids)
        )
        with self.lock:
            last, cause, silent = "no reply", "timeout", ids[0] if ids else None
            for attempt in range(self.retries + 1):
                self.counters["transactions"] += 1
                got: dict[int, bytes] = {}
                for s in self._exchange(packet):
                    if s.instruction == p.STATUS and s.dxl_id not in got:
                        got[s.dxl_id] = s if s.crc_ok and len(s.params) == 1 + length else None
                # the replies come in ID order: the first one missing or bad is the culprit
                bad = next((i for i in ids if got.get(i) is None), None)
                if bad is None:
                    return {i: bytes(got[i].params[1:]) for i in ids}
                silent = bad
                if bad in got:
                    last, cause = "[TxRxResult] Incorrect status packet!", "corrupt"
                    self.counters["corrupt"] += 1
                else:
                    last, cause = "[TxRxResult] There is no status packet!", "timeout"
                    self.counters["timeouts"] += 1
                if attempt < self.retries:
                    self.counters["retries"] += 1
                    msg = "retry %d/%d of %s on servo %s: %s"
                    log.warning(msg, attempt + 1, self.retries, what, ",".join(map(str, ids)), last)
            raise BusError(
                f"servo {','.join(map(str, ids))} did not answer {what} after "
                f"{self.retries + 1} attempts ({last}); check the port, baud rate "
                f"({self.baud_rate}), ID and power",
                servo=silent,
                cause=cause,
            )

    def sync_write(self, reg: Register, values: Mapping[int, int]) -> None:
        """SYNC_WRITE one register to several servos (no reply; verify by reading back)."""
        payload = b"".join(bytes([i]) + p.le(reg.to_raw(v), reg.size) for i, v in values.items())
        params = p.le(reg.address, 2) + p.le(reg.size, 2) + payload
        with self.lock:
            if p.needs_stuffing(bytes([p.SYNC_WRITE]) + params):
                self.counters["stuffed"] += 1
            self._send(p.build_packet(p.BROADCAST_ID, p.SYNC_WRITE, params))

    def broadcast_write(self, reg: Register, value: int) -> None:
        """WRITE to the broadcast ID (every servo, no reply): emergency torque off."""
        with self.lock:
            self._send(
                p.build_packet(
                    p.BROADCAST_ID,
                    p.WRITE,
                    p.le(reg.address, 2) + p.le(reg.to_raw(value), reg.size),
                )
            )

    def reboot(self, dxl_id: int) -> None:
        """REBOOT (clears a hardware error; torque comes back off)."""
        with self.lock:
            self._transact("REBOOT", dxl_id, p.build_packet(dxl_id, p.REBOOT), 0)
            self.alerts.discard(dxl_id)
