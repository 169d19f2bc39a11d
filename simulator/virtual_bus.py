"""A Dynamixel Protocol 2.0 bus of virtual servos: the packet logic, and a pty server.

:class:`ServoBus` is the bus itself: it executes instruction packets
(:meth:`ServoBus.handle`) on the addressed :class:`VirtualServo` objects and returns their
status packets, with faults (corrupted or dropped replies) drawn from a seeded
``numpy.random.Generator`` (:meth:`ServoBus.deliver`).  Two front ends share it:

* :class:`VirtualBus` serves it on a pseudo-terminal from a background thread, so the
  real dynamixel-sdk (and any other Dynamixel tool) opens the pty's slave path as if it
  were a U2D2 adapter;
* :class:`gonio.simulator.loopback.LoopbackTransport` calls it in-process, without a pty
  or a thread (fast rig unit tests).

The servos keep time on the bus's clock (:mod:`gonio.simulator.servo_clock`): the wall
clock ``time_scale`` times faster, or, with ``time_scale="virtual"``, a virtual clock
that advances only by :meth:`ServoBus.sleep` (settle times) and by polled motion: an
instruction that reads a moving servo (READ, SYNC_READ, FAST_SYNC_READ, BULK_READ) first
brings servo time to the end of the polled servos' commanded moves, so the client finds
them arrived (or stopped by the fault that was due on the way) without waiting.

Example
-------
>>> with VirtualBus([1, 2, 3, 4], seed=0) as bus:   # doctest: +SKIP
...     port = bus.port          # e.g. "/dev/pts/7": give it to PortHandler
"""

from __future__ import annotations

import fcntl
import os
import select
import struct
import sys
import termios
import threading
import tty
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from gonio.rig import protocol as p
from gonio.simulator.servo_clock import ServoClock, TimeScale, make_clock
from gonio.simulator.servo_model import VirtualServo

_READS = (p.READ, p.SYNC_READ, p.FAST_SYNC_READ, p.BULK_READ)


@dataclass
class BusStats:
    """Counters of what the bus saw and did (for tests and the CLI)."""

    packets: int = 0
    crc_errors: int = 0
    replies: int = 0
    corrupted: int = 0
    dropped: int = 0
    delayed: int = 0
    wrong_baud: int = 0
    instructions: dict[int, int] = field(default_factory=dict)


# Linux keeps a tty's speed as a number in struct termios2 (c_ispeed, c_ospeed), whether
# the client set it with a POSIX Bxxx constant or with BOTHER (a custom speed, as Rust's
# serialport crate does); tcgetattr only shows BOTHER then.  Layout and ioctl numbers
# from the UAPI headers (asm-generic termbits.h / ioctls.h; x86, arm and riscv use them).
_TERMIOS2 = struct.Struct("=4IB19s2I")
_TCGETS2 = (2 << 30) | (_TERMIOS2.size << 16) | (ord("T") << 8) | 0x2A
_C_OSPEED = struct.Struct("=I")  # the last field of struct termios2
_C_OSPEED_AT = _TERMIOS2.size - _C_OSPEED.size
_LINUX = sys.platform.startswith("linux")
_POSIX_SPEEDS = {
    getattr(termios, n): int(n[1:]) for n in dir(termios) if n[:1] == "B" and n[1:].isdigit()
}


def tty_speed(fd: int) -> int | None:
    """The output speed (bit/s) the kernel keeps for the tty of ``fd``.

    On a pty master this is the slave's setting (the client's).  Read with the ``TCGETS2``
    ioctl on Linux, so that a speed set through ``termios2``/``BOTHER`` is seen as the
    number it is; elsewhere (or if the ioctl fails) from ``tcgetattr``'s speed constant.
    None when the speed cannot be told.
    """
    if _LINUX:
        try:
            buf = bytearray(_TERMIOS2.size)  # filled in place: cheaper than a bytes copy
            fcntl.ioctl(fd, _TCGETS2, buf, True)
            return _C_OSPEED.unpack_from(buf, _C_OSPEED_AT)[0]
        except OSError:
            pass
    try:
        return _POSIX_SPEEDS.get(termios.tcgetattr(fd)[5])
    except termios.error:
        return None


class ServoBus:
    """Virtual servos on one bus: execute instruction packets, return status packets.

    Parameters
    ----------
    servos
        IDs (each gets a ``model`` servo) or ready :class:`VirtualServo` objects.
    model, firmware
        Model name and firmware version of servos created from IDs.
    fault_rate
        Probability that a status packet is corrupted (one bit flipped) or dropped, half
        each.
    delay_rate, delay_s
        Probability and length of a delayed reply (keep ``delay_s`` below the client's
        timeout, see dynamixel.md); only a front end with a clock (the pty) waits.
    seed
        Seed of the fault generator.
    time_scale
        Servo time runs this many times faster than the wall clock (to watch a session
        or a test), or ``"virtual"``: servo time advances by the commanded motion and
        :meth:`sleep` only (see the module docstring).
    clock
        A ready :class:`~gonio.simulator.servo_clock.ServoClock` instead of
        ``time_scale``'s.

    Attributes
    ----------
    servo_clock
        The clock the servos keep time on.
    time_scale
        Its speed-up factor, or ``"virtual"``.
    """

    def __init__(
        self,
        servos: Iterable[int | VirtualServo],
        *,
        model: str = "XM430-W350",
        firmware: int = 45,
        fault_rate: float = 0.0,
        delay_rate: float = 0.0,
        delay_s: float = 0.0,
        seed: int | None = None,
        time_scale: TimeScale = 1.0,
        clock: ServoClock | None = None,
    ) -> None:
        if not 0.0 <= fault_rate <= 1.0:
            raise ValueError(f"fault_rate must be in [0, 1], got {fault_rate}")
        self.servo_clock: ServoClock = clock if clock is not None else make_clock(time_scale)
        self.time_scale: TimeScale = self.servo_clock.time_scale
        self.servos: dict[int, VirtualServo] = {}
        for s in servos:
            if not isinstance(s, VirtualServo):
                s = VirtualServo(int(s), model=model, firmware=firmware, clock=self.clock)
            else:
                s.clock = self.clock
            if s.dxl_id in self.servos:
                raise ValueError(f"duplicate virtual servo ID {s.dxl_id}")
            self.servos[s.dxl_id] = s
        self.fault_rate = fault_rate
        self.delay_rate = delay_rate
        self.delay_s = delay_s
        self.rng = np.random.default_rng(seed)
        self.stats = BusStats()

    def clock(self) -> float:
        """Servo time (s) since the bus was made (see :attr:`servo_clock`)."""
        return self.servo_clock.now()

    def sleep(self, seconds: float) -> None:
        """Let ``seconds`` (s) of servo time pass: waited on a scaled wall clock, added at
        once on a virtual one (a session's settle time)."""
        self.servo_clock.sleep(seconds)

    @property
    def virtual(self) -> bool:
        """Whether servo time is virtual (advanced by motion, not by the wall clock)."""
        return self.time_scale == "virtual"

    def _catch_up(self, ids: Iterable[int]) -> None:
        """Servo time to the end of the moves of the polled servos ``ids`` (virtual
        clock; a scaled clock ignores it)."""
        ends = [
            t
            for i in ids
            if (s := self.servos.get(i)) is not None and (t := s.motion_end()) is not None
        ]
        if ends:
            self.servo_clock.catch_up(max(ends))

    def servo_states(self) -> dict[int, tuple[int, int]]:
        """The servos' physical truth, by ID: (Present Position in pulses, sign of the
        horn's last move in pulses: +1, -1, 0 never moved).

        What the as-built world's pose provider reads (not the controller's view): the
        side of its backlash each gear train rests on is not in any register.
        """
        return {i: s.true_state() for i, s in self.servos.items()}

    def torque(self) -> dict[int, int]:
        """Torque Enable of every servo, by ID."""
        return {i: s.get("torque_enable") for i, s in self.servos.items()}

    def deliver(self, replies: list[bytes]) -> tuple[list[bytes], float]:
        """Apply the bus faults to status packets on their way back.

        Returns
        -------
        replies
            What reaches the client (dropped ones left out, corrupted ones with a bit
            flipped), in order.
        delay
            How long (s) the front end should stay silent before sending them.
        """
        out: list[bytes] = []
        delay = 0.0
        for r in replies:
            self.stats.replies += 1
            if self.fault_rate and self.rng.random() < self.fault_rate:
                if self.rng.random() < 0.5:
                    self.stats.dropped += 1
                    continue
                self.stats.corrupted += 1
                r = bytearray(r)
                r[int(self.rng.integers(4, len(r)))] ^= 1 << int(self.rng.integers(0, 8))
                r = bytes(r)
            if self.delay_rate and self.rng.random() < self.delay_rate:
                self.stats.delayed += 1
                delay += self.delay_s
            out.append(r)
        return out, delay

    def _live(self, dxl_id: int) -> VirtualServo | None:
        s = self.servos.get(dxl_id)
        return None if s is None or s.silent else s

    def handle(self, pkt: p.Packet) -> list[bytes]:
        """Execute one instruction packet; return the status packets to send, in order."""
        st = self.stats
        st.packets += 1
        st.instructions[pkt.instruction] = st.instructions.get(pkt.instruction, 0) + 1
        bid = pkt.dxl_id
        if not pkt.crc_ok:
            st.crc_errors += 1
            s = self._live(bid)
            return [p.build_status(bid, s.error_byte(p.ERR_CRC))] if s else []
        inst, prm = pkt.instruction, pkt.params
        if inst in _READS:
            self._catch_up(self._polled(bid, inst, prm))

        if inst == p.PING:
            targets = sorted(self.servos) if bid == p.BROADCAST_ID else [bid]
            return [
                p.build_status(i, s.error_byte(), s.ping_data())
                for i in targets
                if (s := self._live(i)) is not None
            ]
        if inst in (p.SYNC_READ, p.FAST_SYNC_READ, p.SYNC_WRITE, p.BULK_READ, p.BULK_WRITE):
            return self._group(inst, prm) if bid == p.BROADCAST_ID else []

        targets = sorted(self.servos) if bid == p.BROADCAST_ID else [bid]
        replies = []
        for i in targets:
            s = self._live(i)
            if s is None:
                continue
            level = s.get_u("status_return_level")
            if inst == p.READ:
                if len(prm) != 4:
                    err, data = s.error_byte(p.ERR_DATA_LENGTH), b""
                else:
                    err, data = s.read(p.from_le(prm[0:2]), p.from_le(prm[2:4]))
                if level >= 1 and bid != p.BROADCAST_ID:
                    replies.append(p.build_status(i, err, data))
                continue
            if inst in (p.WRITE, p.REG_WRITE):
                if len(prm) < 3:
                    err = s.error_byte(p.ERR_DATA_LENGTH)
                elif inst == p.WRITE:
                    err = s.write(p.from_le(prm[0:2]), prm[2:])
                else:
                    err = s.reg_write(p.from_le(prm[0:2]), prm[2:])
            elif inst == p.ACTION:
                err = s.action()
            elif inst == p.REBOOT:
                err = s.reboot()
            elif inst == p.FACTORY_RESET:
                err = s.factory_reset(prm[0] if prm else 0xFF)
            elif inst == p.CLEAR:
                ok = prm == bytes([0x01, 0x44, 0x58, 0x4C, 0x22])
                err = s.clear_multi_turn() if ok else s.error_byte(p.ERR_DATA_LIMIT)
            else:
                err = s.error_byte(p.ERR_INSTRUCTION)
            if level >= 2 and bid != p.BROADCAST_ID:
                replies.append(p.build_status(i, err))
        return replies

    def _polled(self, bid: int, inst: int, prm: bytes) -> list[int]:
        """IDs a read instruction addresses (malformed parameters: none)."""
        if inst == p.READ:
            return sorted(self.servos) if bid == p.BROADCAST_ID else [bid]
        if bid != p.BROADCAST_ID:
            return []
        if inst == p.BULK_READ:
            return [prm[k] for k in range(0, len(prm) - 4, 5)]
        return list(prm[4:])  # SYNC_READ, FAST_SYNC_READ: the IDs follow address, length

    def _group(self, inst: int, prm: bytes) -> list[bytes]:
        if inst in (p.SYNC_READ, p.FAST_SYNC_READ, p.SYNC_WRITE):
            if len(prm) < 4:
                return []
            addr, n = p.from_le(prm[0:2]), p.from_le(prm[2:4])
            rest = prm[4:]
            if inst == p.SYNC_WRITE:
                for k in range(0, len(rest) - n, n + 1):
                    s = self._live(rest[k])
                    if s is not None:
                        s.write(addr, rest[k + 1 : k + 1 + n])
                return []
            reads = [(i, addr, n) for i in rest]
        elif inst == p.BULK_WRITE:
            k = 0
            while k + 5 <= len(prm):
                i, addr, n = prm[k], p.from_le(prm[k + 1 : k + 3]), p.from_le(prm[k + 3 : k + 5])
                s = self._live(i)
                if s is not None:
                    s.write(addr, prm[k + 5 : k + 5 + n])
                k += 5 + n
            return []
        else:  # BULK_READ
            reads = [
                (prm[k], p.from_le(prm[k + 1 : k + 3]), p.from_le(prm[k + 3 : k + 5]))
                for k in range(0, len(prm) - 4, 5)
            ]
        results = []
        for i, addr, n in reads:
            s = self._live(i)
            if s is None or s.get_u("status_return_level") < 1:
                continue
            err, data = s.read(addr, n)
            results.append((i, err, data))
        if inst != p.FAST_SYNC_READ:
            return [p.build_status(i, err, data) for i, err, data in results]
        return [self._fast_reply(results)] if results else []

    @staticmethod
    def _fast_reply(results: list[tuple[int, int, bytes]]) -> bytes:
        """One FAST_SYNC_READ status packet: per device ERR ID data CRC, CRCs running."""
        length = 1 + sum(2 + len(d) + 2 for _, _, d in results)
        buf = bytearray(p.HEADER + bytes([p.BROADCAST_ID, length & 0xFF, length >> 8, p.STATUS]))
        for i, err, data in results:
            buf += bytes([err, i]) + data
            crc = p.crc16(buf)
            buf += bytes([crc & 0xFF, crc >> 8])
        return bytes(buf)


class VirtualBus(ServoBus):
    """A :class:`ServoBus` behind a pty, served by a background thread.

    Parameters
    ----------
    servos, model, firmware, fault_rate, delay_rate, delay_s, seed, time_scale, clock
        As for :class:`ServoBus`.
    baud_rate
        The servos' baud rate; a client whose port is set to another rate is not heard
        (as on a real bus, where it would only see garbage).  The client's rate is read
        as the kernel keeps it (:func:`tty_speed`), however the client set it.
    """

    def __init__(
        self,
        servos: Iterable[int | VirtualServo],
        *,
        model: str = "XM430-W350",
        firmware: int = 45,
        baud_rate: int = 1_000_000,
        fault_rate: float = 0.0,
        delay_rate: float = 0.0,
        delay_s: float = 0.0,
        seed: int | None = None,
        time_scale: TimeScale = 1.0,
        clock: ServoClock | None = None,
    ) -> None:
        super().__init__(
            servos,
            model=model,
            firmware=firmware,
            fault_rate=fault_rate,
            delay_rate=delay_rate,
            delay_s=delay_s,
            seed=seed,
            time_scale=time_scale,
            clock=clock,
        )
        self.baud_rate = baud_rate
        self._speed = getattr(termios, f"B{baud_rate}", None)
        self._framer = p.Framer()
        self._master = self._slave = -1
        self._wake_r = self._wake_w = -1
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.port = ""

    # ------------------------------------------------------------- lifecycle
    def start(self) -> VirtualBus:
        """Open the pty and start serving; ``self.port`` is the slave path."""
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # at once, before a client can open it
        if self._speed is not None:
            attrs = termios.tcgetattr(self._slave)
            attrs[4] = attrs[5] = self._speed
            termios.tcsetattr(self._slave, termios.TCSANOW, attrs)
        self.port = os.ttyname(self._slave)
        self._wake_r, self._wake_w = os.pipe()
        self._stop.clear()
        self._thread = threading.Thread(
            target=self._serve, name="virtual-dynamixel-bus", daemon=True
        )
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving and close the pty."""
        if self._thread is None:
            return
        self._stop.set()
        os.write(self._wake_w, b"x")
        self._thread.join(timeout=5)
        self._thread = None
        for fd in (self._master, self._slave, self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self) -> VirtualBus:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # ------------------------------------------------------------- serving
    def _serve(self) -> None:
        poller = select.poll()
        poller.register(self._master, select.POLLIN)
        poller.register(self._wake_r, select.POLLIN)
        while not self._stop.is_set():
            for fd, _ in poller.poll(1000):
                if fd == self._wake_r:
                    return
                try:
                    data = os.read(self._master, 4096)
                except OSError:
                    continue
                if self._speed is not None and tty_speed(self._master) != self.baud_rate:
                    self.stats.wrong_baud += 1  # the servos hear only noise at this rate
                    self._framer.clear()
                    continue
                for pkt in self._framer.feed(data):
                    self._send(self.handle(pkt))

    def _send(self, replies: list[bytes]) -> None:
        out, delay = self.deliver(replies)
        if delay:
            # simulating a slow servo: the bus really is silent meanwhile
            self._stop.wait(delay)
        if out:
            try:
                os.write(self._master, b"".join(out))
            except OSError:
                pass
