"""Light switches of a real rig: a relay on a serial line, or the operator.

Dark frames need the rig's light off (:class:`gonio.devices.Light`); a simulated camera
switches its own light.  A lab rig has one of

- :class:`SerialRelayLight`: a USB/serial relay board (the common CH340 "LCUS" boards,
  or a microcontroller on a GPIO line) that takes a fixed command for on and for off;
  the commands, baud rate and settle time are configurable;
- :class:`OperatorLight`: nobody's relay, the operator at the terminal switches it and
  presses Enter.

:func:`open_light` builds one from the ``--light`` option of ``gonio capture run``:
``relay:PORT[,on=HEX][,off=HEX][,baud=N][,settle=S]``, ``operator`` or ``none``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import click

from gonio.errors import CameraError, ConfigError

__all__ = [
    "DEFAULT_OFF",
    "DEFAULT_ON",
    "OperatorLight",
    "SerialRelayLight",
    "open_light",
    "parse_light_spec",
]

#: The LCUS-1 USB relay's commands (start byte, relay 1, state, checksum).
DEFAULT_ON = bytes.fromhex("A00101A2")
DEFAULT_OFF = bytes.fromhex("A00100A1")


class SerialRelayLight:
    """A light switched by a relay that takes one command for on and one for off.

    Implements :class:`gonio.devices.Light`.

    Parameters
    ----------
    port
        Serial port (``/dev/ttyUSB0``, ``COM3``, or any pyserial URL).
    on_command, off_command
        The bytes that close and open the relay.
    baud_rate
        Line speed, baud.
    settle_s
        Time the light needs to reach its level (or to go dark) after switching, s.
    sleep
        Waits ``settle_s`` (the wall clock; injectable for tests).
    serial_factory
        ``serial_for_url``-like factory (tests pass one; default pyserial's).
    """

    def __init__(
        self,
        port: str,
        on_command: bytes = DEFAULT_ON,
        off_command: bytes = DEFAULT_OFF,
        *,
        baud_rate: int = 9600,
        settle_s: float = 0.5,
        sleep: Callable[[float], None] = time.sleep,
        serial_factory: Callable[..., Any] | None = None,
    ) -> None:
        if not on_command or not off_command:
            raise ConfigError("light relay: the on and off commands must not be empty")
        if on_command == off_command:
            raise ConfigError("light relay: the on and off commands are the same bytes")
        self.port = port
        self.on_command = bytes(on_command)
        self.off_command = bytes(off_command)
        self.settle_s = float(settle_s)
        self._sleep = sleep
        if serial_factory is None:
            import serial

            serial_factory = serial.serial_for_url
        try:
            self._serial = serial_factory(port, baudrate=int(baud_rate), timeout=1.0)
        except Exception as exc:  # noqa: BLE001 - pyserial raises SerialException/OSError
            raise CameraError(f"light relay on {port}: cannot open the port ({exc})") from exc
        self.is_on: bool | None = None

    def set_light(self, on: bool) -> None:
        """Send the relay's command and wait ``settle_s``."""
        cmd = self.on_command if on else self.off_command
        try:
            n = self._serial.write(cmd)
            self._serial.flush()
        except Exception as exc:  # noqa: BLE001
            raise CameraError(f"light relay on {self.port}: write failed ({exc})") from exc
        if n is not None and n != len(cmd):
            raise CameraError(
                f"light relay on {self.port}: wrote {n} of {len(cmd)} bytes of the command"
            )
        self.is_on = bool(on)
        if self.settle_s > 0:
            self._sleep(self.settle_s)

    def close(self) -> None:
        """Close the port (idempotent)."""
        ser, self._serial = getattr(self, "_serial", None), None
        if ser is not None:
            ser.close()


class OperatorLight:
    """The operator switches the light: asked at the terminal, confirmed with Enter.

    Implements :class:`gonio.devices.Light`.  The first call for "on" when the light is
    on already (the session starts lit) asks nothing.
    """

    def __init__(self, *, assume_on: bool = True) -> None:
        self.is_on: bool | None = True if assume_on else None

    def set_light(self, on: bool) -> None:
        """Ask the operator to switch the light ``on``/off and wait for Enter."""
        if self.is_on is not None and self.is_on == bool(on):
            return
        state = "ON" if on else "OFF (leave the room as it is during the session)"
        try:
            click.prompt(
                f"Switch the rig's light {state}, then press Enter",
                default="",
                show_default=False,
                prompt_suffix=" ",
            )
        except (click.Abort, EOFError) as exc:
            # nobody answered: the frames must not be shot with the light in doubt
            raise CameraError(
                f"the operator did not confirm the light {'on' if on else 'off'}"
            ) from exc
        self.is_on = bool(on)

    def close(self) -> None:
        """Nothing to release."""


def parse_light_spec(spec: str) -> dict[str, Any]:
    """The ``--light`` option as a dict: ``{"kind": "relay"|"operator"|"none", ...}``.

    ``relay:PORT[,on=HEX][,off=HEX][,baud=N][,settle=S]`` (HEX: the command bytes, e.g.
    ``A00101A2``; S in seconds).

    Raises
    ------
    ConfigError
        Naming the option, the part that is wrong and what was expected.
    """
    text = spec.strip()
    if text.lower() in ("none", "operator"):
        return {"kind": text.lower()}
    if not text.lower().startswith("relay:"):
        raise ConfigError(f"--light {spec!r}: expected relay:PORT, operator or none")
    port, *opts = text[len("relay:") :].split(",")
    if not port.strip():
        raise ConfigError(f"--light {spec!r}: relay:PORT needs a serial port (e.g. /dev/ttyUSB0)")
    out: dict[str, Any] = {"kind": "relay", "port": port.strip()}
    for opt in opts:
        key, sep, val = opt.partition("=")
        key = key.strip().lower()
        try:
            if not sep:
                raise ValueError("expected key=value")
            if key in ("on", "off"):
                out[key] = bytes.fromhex(val.strip())
            elif key == "baud":
                out["baud"] = int(val)
                if out["baud"] <= 0:
                    raise ValueError("must be a positive baud rate")
            elif key == "settle":
                out["settle"] = float(val)
                if not (math.isfinite(out["settle"]) and 0 <= out["settle"] <= 600):
                    raise ValueError("must be a finite time in [0, 600] s")
            else:
                raise ValueError("unknown key (on, off, baud, settle)")
        except ValueError as exc:
            raise ConfigError(f"--light {spec!r}: {opt.strip()!r}: {exc}") from None
    return out


def open_light(spec: str) -> SerialRelayLight | OperatorLight | None:
    """The light switch ``spec`` names (see :func:`parse_light_spec`); None for ``none``."""
    p = parse_light_spec(spec)
    if p["kind"] == "none":
        return None
    if p["kind"] == "operator":
        return OperatorLight()
    return SerialRelayLight(
        p["port"],
        p.get("on", DEFAULT_ON),
        p.get("off", DEFAULT_OFF),
        baud_rate=p.get("baud", 9600),
        settle_s=p.get("settle", 0.5),
    )
