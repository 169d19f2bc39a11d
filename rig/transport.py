"""The one owner of the Dynamixel bus: dynamixel-sdk behind a lock, with retries.

dynamixel-sdk's ``PortHandler`` is not thread-safe (``is_using`` is a flag, not a lock),
times out on a loaded CPU, returns unsigned values, and (4.1.0) never byte-stuffs what
it sends.  :class:`Transport` wraps ``PortHandler`` / ``Protocol2PacketHandler`` /
``GroupSyncRead`` / ``GroupSyncWrite`` so that every access

- takes the bus lock,
- is retried on corrupt replies and timeouts (counted, and logged on logger
  ``gonio.rig.bus``),
- goes through the control table (:mod:`gonio.rig.control_table`) with signed
  conversions,
- is stuffed correctly (packets whose payload contains ``FF FF FD`` are built by
  :func:`gonio.rig.protocol.build_packet` and written directly),
- uses the configured timeout instead of the SDK's global ``LATENCY_TIMER``,
- fails with :class:`~gonio.errors.BusError` (``servo``, ``cause``) when a servo does not
  answer after every retry or refuses an instruction.

It implements :class:`gonio.rig.bus.BusTransport`, the interface the rig is given.
"""

from __future__ import annotations

import fcntl
import logging
import select
import threading
import time
from collections import Counter
from collections.abc import Iterable, Mapping

import serial
from dynamixel_sdk import (
    COMM_RX_CORRUPT,
    COMM_RX_TIMEOUT,
    COMM_SUCCESS,
    GroupSyncRead,
    GroupSyncWrite,
    PacketHandler,
    PortHandler,
)

from gonio.errors import BusError, RigError
from gonio.rig import protocol
from gonio.rig.control_table import Register

log = logging.getLogger("gonio.rig.bus")

_RETRYABLE = (COMM_RX_TIMEOUT, COMM_RX_CORRUPT)


def sync_read_culprit(
    ids: tuple[int, ...], failures: list[tuple[int | None, int]], cause: str
) -> tuple[int | None, str]:
    """The servo to name, and why, after every attempt of a SYNC_READ failed.

    Parameters
    ----------
    ids
        The IDs read, in the order their replies come.
    failures
        One ``(index into ids of the first reply that failed, or None; SDK result)`` per
        failed attempt, in order.
    cause
        What the attempts' classification gave (the last attempt's): ``"timeout"``,
        ``"corrupt"`` or ``"port"``.

    Returns
    -------
    (servo or None, cause)
        The servo at which the attempt that got furthest stopped: every servo before it
        answered in that attempt, so it is the one evidence points to (the last attempt
        alone can stop earlier, at a servo whose reply was merely late on a loaded
        machine).  ``"timeout"`` if that servo ever failed with no reply at all: a silent
        servo's wait can also end with another servo's reply half-received (the SDK
        calls that corrupt), which says nothing about the silent one.
    """
    found = [(k, r) for k, r in failures if k is not None]
    if not found or cause == "port":
        return None, cause
    furthest = max(k for k, _ in found)
    timed_out = any(k == furthest and r == COMM_RX_TIMEOUT for k, r in found)
    return ids[furthest], "timeout" if timed_out else cause


class _Port(PortHandler):
    """PortHandler with a per-instance reply timeout.

    The SDK computes ``tx_time * bytes + 2 * LATENCY_TIMER + 2 ms`` from a module global;
    patching that global would change every port in the process, so the budget is an
    attribute here.
    """

    def __init__(self, port_name: str, latency_timer_ms: float, timeout_ms: float | None) -> None:
        super().__init__(port_name)
        self.latency_timer_ms = latency_timer_ms
        self.fixed_timeout_ms = timeout_ms

    def readPort(self, length):  # noqa: N802 - SDK name
        """Up to ``length`` bytes, waiting (in ``select``) until the first one comes or
        the packet's timeout passes.

        The SDK opens the port non-blocking and its ``rxPacket`` calls this in a loop
        until a status arrives or the timeout passes: a busy loop that holds a core (and
        the GIL: a virtual bus served from a thread of this process then gets it only
        at the interpreter's switch interval, ~5 ms per reply).  Waiting in ``select``
        ends at the same deadline and returns the same bytes: what the loop would have
        read by then.
        """
        ser = self.ser
        if length > 0 and ser.fd is not None:
            # the SDK's own clock (wall time in ms): the deadline its isPacketTimeout checks
            left_ms = self.packet_start_time + self.packet_timeout - self.getCurrentTime()
            if left_ms > 0:
                try:
                    select.select([ser.fd], [], [], left_ms / 1000.0)
                except (OSError, ValueError):
                    pass  # a closed port: the read below says so as the SDK's would
        return ser.read(length)

    def setPacketTimeout(self, packet_length):  # noqa: N802 - SDK name
        self.packet_start_time = self.getCurrentTime()
        if self.fixed_timeout_ms is not None:
            self.packet_timeout = self.tx_time_per_byte * packet_length + self.fixed_timeout_ms
        else:
            self.packet_timeout = (
                self.tx_time_per_byte * packet_length + 2.0 * self.latency_timer_ms + 2.0
            )


class Transport:
    """Bus owner: open the port, read and write registers with retries.

    Parameters
    ----------
    port
        Serial device path (``/dev/ttyUSB0``, or a virtual bus's pty).
    baud_rate
        Bits per second; must match the servos' Baud Rate register.
    retries
        Extra attempts after a timeout or corrupt reply.
    timeout_ms
        Fixed reply timeout (plus transmission time); None: the SDK formula with
        ``latency_timer_ms``.
    latency_timer_ms
        USB adapter latency the timeout budgets for (FTDI default 16 ms).

    Attributes
    ----------
    counters
        ``Counter`` of ``"retries"``, ``"timeouts"``, ``"corrupt"``, ``"transactions"``,
        ``"stuffed"``.
    alerts
        IDs whose last status packet had the alert bit (read register 70).
    """

    def __init__(
        self,
        port: str,
        baud_rate: int = 1_000_000,
        *,
        retries: int = 3,
        timeout_ms: float | None = None,
        latency_timer_ms: float = 16.0,
    ) -> None:
        self.port_name = port
        self.baud_rate = baud_rate
        self.retries = retries
        self.lock = threading.RLock()
        self.counters: Counter[str] = Counter()
        self.alerts: set[int] = set()
        self._port = _Port(port, latency_timer_ms, timeout_ms)
        self._ph = PacketHandler(2.0)
        self._sync_reads: dict[tuple[int, int, tuple[int, ...]], GroupSyncRead] = {}

    # ------------------------------------------------------------- lifecycle
    def open(self) -> Transport:
        """Open the serial port at the baud rate.

        Raises
        ------
        BusError
            If the port does not exist or cannot be opened (``cause="port"``).
        RigError
            If the baud rate is not one dynamixel-sdk supports.
        """
        if self._port.getCFlagBaud(self.baud_rate) <= 0:
            raise RigError(f"baud rate {self.baud_rate} is not supported by dynamixel-sdk")
        self._port.baudrate = self.baud_rate
        try:
            self._port.openPort()
        except (serial.SerialException, OSError) as exc:
            raise BusError(
                f"cannot open serial port {self.port_name!r}: {exc}", cause="port"
            ) from None
        # One controller per bus: two processes' packets interleaved and one moved the
        # arms while the other failed mid-command.  pyserial's own `exclusive=True` is
        # this flock; dynamixel-sdk opens the port without it.
        fd = getattr(getattr(self._port, "ser", None), "fileno", lambda: None)()
        if fd is not None:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                self._port.closePort()
                raise BusError(
                    f"serial port {self.port_name!r} is in use by another process (another "
                    "gonio rig command or session?); wait for it to finish or stop it first",
                    cause="port",
                ) from None
            except OSError:  # a port type without locks: nothing to hold
                pass
        return self

    def close(self) -> None:
        """Close the port (idempotent)."""
        with self.lock:
            if self._port.is_open:
                self._port.closePort()

    @property
    def is_open(self) -> bool:
        return bool(self._port.is_open)

    def __enter__(self) -> Transport:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    def reset(self) -> None:
        """Recover after an interrupted transaction (e.g. a signal mid-read)."""
        with self.lock:
            self._port.is_using = False
            if self._port.is_open:
                self._port.clearPort()

    # ------------------------------------------------------------- core
    def _status(self, what: str, dxl_id: int, result: int, error: int) -> None:
        if error & protocol.ERR_ALERT:
            self.alerts.add(dxl_id)
        protocol.check_status(what, dxl_id, error)

    def _drain_late_reply(self) -> None:
        """Wait out and drop a reply that arrives after its timeout.

        Protocol 2.0 status packets do not say which instruction they answer, and the SDK
        only checks the ID: a late reply to the failed attempt would be taken as the
        retry's (a firmware READ parsed as a PING gave model 48429 for 1020 on a loaded
        machine).  Waiting one more timeout before clearing the input keeps the retry's
        reply its own; this costs time only after a failure.
        """
        port = self._port
        wait_ms = port.fixed_timeout_ms
        if wait_ms is None:
            wait_ms = 2.0 * port.latency_timer_ms + 2.0
        time.sleep(wait_ms / 1000.0)
        if port.is_open:
            port.clearPort()

    def _attempt(self, what: str, dxl_id: int | str, fn):
        """Run ``fn() -> (value, result, error)`` with retries; return (value, error)."""
        last, cause = None, "port"
        for attempt in range(self.retries + 1):
            self.counters["transactions"] += 1
            value, result, error = fn()
            if result == COMM_SUCCESS and (error & 0x7F) != protocol.ERR_CRC:
                if attempt:
                    log.info("%s on servo %s succeeded after %d retries", what, dxl_id, attempt)
                return value, error
            last = self._ph.getTxRxResult(result) if result != COMM_SUCCESS else "CRC error"
            self.counters["timeouts" if result == COMM_RX_TIMEOUT else "corrupt"] += 1
            if result not in _RETRYABLE and result != COMM_SUCCESS:
                cause = "port"  # busy or failed to send: retrying would not help
                break
            cause = "timeout" if result == COMM_RX_TIMEOUT else "corrupt"
            if attempt < self.retries:
                self.counters["retries"] += 1
                self._drain_late_reply()
                # an absent ID during a scan is expected: keep PING retries out of warnings
                level = logging.INFO if what == "PING" else logging.WARNING
                log.log(
                    level,
                    "retry %d/%d of %s on servo %s: %s",
                    attempt + 1,
                    self.retries,
                    what,
                    dxl_id,
                    last,
                )
        raise BusError(
            f"servo {dxl_id} did not answer {what} after {self.retries + 1} attempts "
            f"({last}); check the port, baud rate ({self.baud_rate}), ID and power",
            servo=dxl_id if isinstance(dxl_id, int) else None,
            cause=cause,
        )

    # ------------------------------------------------------------- instructions
    def ping(self, dxl_id: int, retries: int | None = None) -> tuple[int, int] | None:
        """(model number, firmware version) of ``dxl_id``, or None if it does not answer."""

        def fn():
            # the PING status carries model (2 bytes) and firmware (1): one transaction
            data, result, error = self._txrx(protocol.build_packet(dxl_id, protocol.PING), 3)
            if result != COMM_SUCCESS:
                return (0, 0), result, error
            return (protocol.from_le(data[:2]), data[2]), result, error

        with self.lock:
            saved = self.retries
            if retries is not None:
                self.retries = retries
            try:
                (model, fw), err = self._attempt("PING", dxl_id, fn)
            except RigError:
                return None
            finally:
                self.retries = saved
            if err & protocol.ERR_ALERT:
                self.alerts.add(dxl_id)
            return model, fw

    def broadcast_ping(self) -> dict[int, tuple[int, int]]:
        """Every servo on the bus: ID -> (model number, firmware).  Takes about 0.8 s."""
        with self.lock:
            found, result = self._ph.broadcastPing(self._port)
            self.counters["transactions"] += 1
            if result not in (COMM_SUCCESS, COMM_RX_TIMEOUT):
                log.warning("broadcast ping: %s", self._ph.getTxRxResult(result))
            return {int(i): (int(v[0]), int(v[1])) for i, v in sorted(found.items())}

    def read_bytes(self, dxl_id: int, address: int, length: int) -> bytes:
        """READ ``length`` raw bytes from ``address``."""
        with self.lock:
            data, err = self._attempt(
                f"READ {address}+{length}",
                dxl_id,
                lambda: self._txrx(
                    protocol.build_packet(
                        dxl_id, protocol.READ, protocol.le(address, 2) + protocol.le(length, 2)
                    ),
                    length,
                ),
            )
            self._status(f"READ {address}", dxl_id, COMM_SUCCESS, err)
            if len(data) != length:
                raise BusError(
                    f"servo {dxl_id} returned {len(data)} bytes for a {length}-byte READ",
                    servo=dxl_id,
                    cause="corrupt",
                )
            return bytes(data)

    def read(self, dxl_id: int, reg: Register) -> int:
        """Read a register; signed registers come back signed."""
        return reg.to_signed(protocol.from_le(self.read_bytes(dxl_id, reg.address, reg.size)))

    def write_bytes(self, dxl_id: int, address: int, data: bytes, what: str = "") -> None:
        """WRITE raw bytes (with correct stuffing) and check the status packet."""
        what = what or f"WRITE {address}"
        with self.lock:
            params = protocol.le(address, 2) + bytes(data)
            stuffed = protocol.needs_stuffing(bytes([protocol.WRITE]) + params)
            if stuffed:
                self.counters["stuffed"] += 1

            def fn():
                # built here, stuffed: the SDK would send FF FF FD in the data unstuffed
                return self._txrx(protocol.build_packet(dxl_id, protocol.WRITE, params), 0)

            _, err = self._attempt(what, dxl_id, fn)
            self._status(what, dxl_id, COMM_SUCCESS, err)

    def write(self, dxl_id: int, reg: Register, value: int) -> None:
        """Write a register value (signed values are encoded as two's complement)."""
        if reg.access != "RW":
            raise RigError(f"register {reg.name} is read-only")
        self.write_bytes(
            dxl_id,
            reg.address,
            protocol.le(reg.to_raw(value), reg.size),
            f"WRITE {reg.name}={value}",
        )

    def _txrx(self, packet: bytes, n_params: int) -> tuple[bytes, int, int]:
        """Send a packet built here and read its status with the SDK: ``(params, result,
        error)``.

        Protocol 2.0 status packets do not name the instruction they answer, and the SDK
        matches replies by ID alone: a reply that missed an earlier attempt's timeout
        and arrives now would be taken for this one's (a late firmware READ parsed as a
        PING gave model 48429 for 1020 on a loaded machine).  A status from this ID with
        another parameter count than this instruction's reply is such a stale reply, and
        is skipped.
        """
        port = self._port
        if port.is_using:
            return b"", -1000, 0  # COMM_PORT_BUSY
        port.is_using = True
        port.clearPort()
        port.writePort(packet)
        port.setPacketTimeout(11 + n_params)
        while True:
            rx, result = self._ph.rxPacket(port, False)
            if result != COMM_SUCCESS:
                return b"", result, 0
            if rx[4] == packet[4] and protocol.from_le(bytes(rx[5:7])) == n_params + 4:
                return bytes(rx[9 : 9 + n_params]), result, rx[8]
            port.is_using = True  # rxPacket released the port; keep it for the next read

    def sync_read(self, ids: Iterable[int], address: int, length: int) -> dict[int, bytes]:
        """SYNC_READ ``length`` bytes at ``address`` from every ID; all or nothing.

        Group reads drop the status ERR byte (no alert bit): read register 70 in the block.
        """
        ids = tuple(ids)
        key = (address, length, ids)
        with self.lock:
            group = self._sync_reads.get(key)
            if group is None:
                group = GroupSyncRead(self._port, self._ph, address, length)
                for i in ids:
                    group.addParam(i)
                self._sync_reads[key] = group

            failures: list[tuple[int | None, int]] = []

            def fn():
                result = group.txRxPacket()
                if result != COMM_SUCCESS:
                    # the SDK reads the replies in ID order and stops at the first that
                    # fails, leaving its data empty: the first short one failed
                    at = next(
                        (k for k, i in enumerate(ids) if len(group.data_dict[i]) != length), None
                    )
                    failures.append((at, result))
                return None, result, 0

            try:
                self._attempt(f"SYNC_READ {address}+{length}", ",".join(map(str, ids)), fn)
            except BusError as exc:
                silent, cause = sync_read_culprit(ids, failures, exc.cause)
                raise BusError(str(exc), servo=silent, cause=cause) from None
            return {i: bytes(group.data_dict[i]) for i in ids}

    def sync_write(self, reg: Register, values: Mapping[int, int]) -> None:
        """SYNC_WRITE one register to several servos (no reply; verify by reading back)."""
        with self.lock:
            payload = b"".join(
                bytes([i]) + protocol.le(reg.to_raw(v), reg.size) for i, v in values.items()
            )
            params = protocol.le(reg.address, 2) + protocol.le(reg.size, 2) + payload
            self.counters["transactions"] += 1
            if protocol.needs_stuffing(bytes([protocol.SYNC_WRITE]) + params):
                self.counters["stuffed"] += 1
                self._raw_send(
                    protocol.build_packet(protocol.BROADCAST_ID, protocol.SYNC_WRITE, params)
                )
                return
            group = GroupSyncWrite(self._port, self._ph, reg.address, reg.size)
            for i, v in values.items():
                group.addParam(i, list(protocol.le(reg.to_raw(v), reg.size)))
            result = group.txPacket()
            if result != COMM_SUCCESS:
                raise BusError(
                    f"SYNC_WRITE {reg.name} failed: {self._ph.getTxRxResult(result)}",
                    cause="port",
                )

    def broadcast_write(self, reg: Register, value: int) -> None:
        """WRITE to the broadcast ID (every servo, no reply): used for emergency torque off."""
        with self.lock:
            pkt = protocol.build_packet(
                protocol.BROADCAST_ID,
                protocol.WRITE,
                protocol.le(reg.address, 2) + protocol.le(reg.to_raw(value), reg.size),
            )
            self._raw_send(pkt)

    def _raw_send(self, packet: bytes) -> None:
        port = self._port
        port.is_using = False
        port.clearPort()
        port.writePort(packet)
        port.ser.flush()

    def reboot(self, dxl_id: int) -> None:
        """REBOOT (clears a hardware error; torque comes back off)."""
        with self.lock:
            _, err = self._attempt(
                "REBOOT", dxl_id, lambda: (None, *self._ph.reboot(self._port, dxl_id))
            )
            self.alerts.discard(dxl_id)
