"""The clock a virtual servo bus keeps its servos' time on: scaled wall clock, or virtual.

Both clocks answer the same three calls, so the servos, the bus and the composition root
do not care which one runs:

* ``now()`` -- servo time (s) since the bus was made;
* ``sleep(seconds)`` -- let ``seconds`` of servo time pass (a settle time);
* ``catch_up(t)`` -- a client is polling servos whose commanded motion ends at servo
  time ``t``.

:class:`ScaledClock` follows the wall clock ``time_scale`` times faster: ``sleep``
waits on the wall clock and ``catch_up`` does nothing (time comes by itself), so a person
can watch the arms move.  :class:`VirtualClock` does not follow the wall clock at all:
``sleep`` adds its seconds at once and ``catch_up`` jumps to ``t``, so a client that polls
a moving servo finds the motion finished, and a session spends no wall time on motion or
settling.  Motion, faults and heating are evaluated at the servo time either way, which
is why a virtual session gives the same journal as a watched one.

Only the servos' time is virtual: the wire is not.  A reply delay of the bus
(``delay_s``) and the client's reply timeouts stay wall-clock times.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Literal, Protocol, runtime_checkable

__all__ = [
    "VIRTUAL",
    "ScaledClock",
    "ServoClock",
    "TimeScale",
    "VirtualClock",
    "make_clock",
    "parse_time_scale",
]

#: The ``time_scale`` that asks for a :class:`VirtualClock`.
VIRTUAL: Literal["virtual"] = "virtual"

#: A bus's speed: a wall-clock speed-up factor (> 0), or ``"virtual"``.
TimeScale = float | Literal["virtual"]


@runtime_checkable
class ServoClock(Protocol):
    """What the servos of a bus keep time on (see the module docstring)."""

    @property
    def time_scale(self) -> TimeScale:
        """The speed-up factor, or ``"virtual"`` (for records)."""
        ...

    def now(self) -> float:
        """Servo time, s."""
        ...

    def sleep(self, seconds: float) -> None:
        """Let ``seconds`` (s) of servo time pass."""
        ...

    def catch_up(self, t: float) -> None:
        """A client polls motion that ends at servo time ``t`` (s)."""
        ...


class ScaledClock:
    """Servo time = wall-clock time since creation times ``time_scale``.

    Parameters
    ----------
    time_scale
        Speed-up factor over the wall clock (> 0, finite).
    """

    def __init__(self, time_scale: float = 1.0) -> None:
        scale = float(time_scale)
        if not (math.isfinite(scale) and scale > 0):
            raise ValueError(f"time_scale must be a positive finite number, got {time_scale!r}")
        self._scale = scale
        self._t0 = time.monotonic()

    @property
    def time_scale(self) -> float:
        return self._scale

    def now(self) -> float:
        """Servo time (s): wall-clock seconds since creation times ``time_scale``."""
        return (time.monotonic() - self._t0) * self._scale

    def sleep(self, seconds: float) -> None:
        """Wait (on the wall clock) until ``seconds`` of servo time have passed."""
        end = self.now() + seconds
        while (left := end - self.now()) > 0:
            time.sleep(left / self._scale)

    def catch_up(self, t: float) -> None:  # noqa: ARG002 - the wall clock gets there itself
        """Nothing: a client polling a moving servo sees it move in (scaled) real time."""


class VirtualClock:
    """Servo time that advances only when told: by settle times and polled motion.

    Starts at 0 s.  Safe to call from the pty server thread and the session's thread.
    """

    def __init__(self) -> None:
        self._t = 0.0
        self._lock = threading.Lock()

    @property
    def time_scale(self) -> Literal["virtual"]:
        return VIRTUAL

    def now(self) -> float:
        """Servo time, s."""
        return self._t

    def sleep(self, seconds: float) -> None:
        """Advance servo time by ``seconds`` (s) at once (a negative value does nothing)."""
        if seconds > 0:
            with self._lock:
                self._t += float(seconds)

    def catch_up(self, t: float) -> None:
        """Advance servo time to ``t`` (s) if it is behind: the polled motion is over."""
        with self._lock:
            if t > self._t:
                self._t = float(t)


#: The largest wall-clock speed-up of a virtual bus: beyond it a move's servo time
#: overflows the integer conversions of the servo model (1e308 crashed its thread), and
#: nothing is left to watch -- "virtual" is the mode that does not wait at all.
MAX_TIME_SCALE = 1e6


def parse_time_scale(value: object) -> TimeScale:
    """A bus speed from a record or an option: ``"virtual"`` or a positive finite float.

    Raises
    ------
    ValueError
        Anything else, with the value in the message.
    """
    if isinstance(value, str) and value.strip().lower() == VIRTUAL:
        return VIRTUAL
    try:
        scale = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        scale = math.nan
    if not (math.isfinite(scale) and 0 < scale <= MAX_TIME_SCALE):
        raise ValueError(
            f"expected 'virtual' or a speed-up factor in (0, {MAX_TIME_SCALE:g}], got {value!r}"
        )
    return scale


def make_clock(time_scale: TimeScale) -> ScaledClock | VirtualClock:
    """The clock of a bus running at ``time_scale`` (see :func:`parse_time_scale`)."""
    scale = parse_time_scale(time_scale)
    return VirtualClock() if scale == VIRTUAL else ScaledClock(float(scale))
