"""The session engine: executes a plan's messages on the devices, publishes documents.

One small loop (:meth:`Engine.execute`): take the plan's next message, run it on the
devices (:mod:`gonio.capture.messages` lists what each does), send the reply back into
the generator -- or throw the device's exception into it, so the plan decides what a
:class:`~gonio.errors.PoseRefused` means.  Documents (``start``, ``shot``,
``pose_done``, ``pose_skipped``, ``fault``, ``stop``) go to the subscribers in order: the
journal writer first, so a document is on disk before a progress display shows it or
the plan moves the rig again.

:func:`run_plan` wraps a plan in the bluesky-style bracket: a ``start`` document, the
plan, a ``fault`` document when a device fails (typed: rig faults and bus errors carry
their servo and error bits as fields), and a finalizer that always sets the light on,
puts the sample back, parks and cuts torque -- after completion, a fault, Ctrl-C or
SIGTERM -- and a ``stop`` document saying which servos did not confirm torque off.
"""

from __future__ import annotations

import contextlib
import signal
import threading
import time
from collections.abc import Callable, Generator, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from gonio.capture.journal import sha256_bytes, write_atomic, xxh3_bytes
from gonio.capture.messages import (
    Captured,
    Checkpoint,
    Emit,
    Move,
    Read,
    SetLight,
    SetTarget,
    Settle,
    Shoot,
)
from gonio.devices import (
    Camera,
    Light,
    MoveResult,
    RigDevice,
    RigState,
    SeededShots,
    TargetChanger,
)
from gonio.errors import BusError, CameraError, RigError, RigFault

__all__ = [
    "Engine",
    "Interrupted",
    "RunOutcome",
    "SessionDevices",
    "Subscriber",
    "fault_record",
    "finalize",
    "run_plan",
]

Subscriber = Callable[[dict[str, Any]], None]


@runtime_checkable
class ForwardKinematics(Protocol):
    """What the session needs of the rig's kinematics: the directions its joints give."""

    def forward(self, joints: Mapping[str, float]) -> tuple[np.ndarray, np.ndarray]:
        """``(wi, wo)`` unit vectors in the sample frame for joint angles in rad."""
        ...


@dataclass
class SessionDevices:
    """The open devices a session runs on (built by the composition root, ``gonio.app``).

    Attributes
    ----------
    rig
        The rig (:class:`gonio.devices.RigDevice`).
    camera
        The camera (:class:`gonio.devices.Camera`); a :class:`~gonio.devices.SeededShots`
        camera is told each shot's (step, frame) before it shoots.
    light
        The switchable light (needed for dark frames), or None.
    target
        The reference-target changer, or None (reference poses then shoot whatever is
        in place).
    kinematics
        The rig's ``gonio.rig.kinematics.Kinematics`` (achieved directions).
    sleep
        Waits a number of seconds of *rig* time: the wall clock for a real rig, the
        servo clock for a virtual bus (``settle_s`` is applied through it).
    read_noise_dn
        ``iso -> DN rms`` of the camera, the adaptive bracket's noise floor (2 DN when
        None).
    files
        Files the devices contribute to the session, path inside it -> bytes: what the
        devices know and the reduction needs (a simulated camera's ``reduction.toml``:
        its camera matrix, board, noise and light).  Written when the session is
        created, and on resume when missing (never over a file that is there).
    clock
        *Rig time* in s: ``time.monotonic`` for a real rig, the virtual bus's servo
        clock for a simulated one (the simulated camera's light drifts with the same
        clock).  When given, every ``shot`` record carries ``rig_time``, read just
        before the frame is shot; None: no ``rig_time``.
    """

    rig: RigDevice
    camera: Camera
    light: Light | None = None
    target: TargetChanger | None = None
    kinematics: ForwardKinematics | None = None
    sleep: Callable[[float], None] = time.sleep
    read_noise_dn: Callable[[float], float] | None = None
    files: Mapping[str, bytes] = field(default_factory=dict)
    clock: Callable[[], float] | None = None

    def noise_floor_dn(self, iso: float | None) -> float:
        """Read noise (DN rms) at ``iso`` (ISO 100 when the camera keeps its own)."""
        if self.read_noise_dn is None:
            return 2.0
        return float(self.read_noise_dn(100.0 if iso is None else float(iso)))


class Interrupted(Exception):
    """SIGTERM arrived: stop after the finalizer."""


@contextlib.contextmanager
def _terminate_as_interrupt() -> Iterator[None]:
    """Turn SIGTERM into an exception in the main thread, so the finalizer runs."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):  # noqa: ARG001
        raise Interrupted(f"signal {signal.Signals(signum).name}")

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


class Engine:
    """Executes plans on one set of devices and publishes their documents.

    Parameters
    ----------
    devices
        The open devices.
    session_dir
        Where :class:`Shoot` stores RAW files (None: shooting is refused).
    subscribers
        Called in order with every document (journal writer first).
    handlers
        Message type -> handler, replacing the engine's own (the dry run answers
        :class:`Shoot` with None and records each move).
    """

    def __init__(
        self,
        devices: SessionDevices,
        session_dir: Path | None = None,
        subscribers: Sequence[Subscriber] = (),
        handlers: Mapping[type, Callable[[Any], Any]] | None = None,
    ) -> None:
        self.devices = devices
        self.session_dir = session_dir
        self.subscribers = list(subscribers)
        self._handlers: dict[type, Callable[[Any], Any]] = {
            Move: self._move,
            Read: self._read,
            Settle: self._settle,
            SetLight: self._set_light,
            SetTarget: self._set_target,
            Shoot: self._shoot,
            Emit: self._publish_msg,
            Checkpoint: self._publish_msg,
        }
        self._handlers.update(handlers or {})

    # -- documents ----------------------------------------------------------------------
    def publish(self, document: Mapping[str, Any]) -> dict[str, Any]:
        """Stamp ``time`` (if missing) and hand the document to every subscriber."""
        doc = dict(document)
        doc.setdefault("time", time.time())
        for s in self.subscribers:
            s(doc)
        return doc

    def _publish_msg(self, msg: Emit | Checkpoint) -> dict[str, Any]:
        return self.publish(msg.document)

    # -- the loop -----------------------------------------------------------------------
    def execute(self, plan: Generator[Any, Any, Any]) -> None:
        """Run ``plan`` to its end; an exception the plan does not handle propagates."""
        reply: Any = None
        error: BaseException | None = None
        while True:
            try:
                msg = plan.throw(error) if error is not None else plan.send(reply)
            except StopIteration:
                return
            reply, error = None, None
            try:
                reply = self._handlers[type(msg)](msg)
            except BaseException as exc:  # noqa: BLE001 - thrown into the plan, which decides
                error = exc

    # -- handlers -----------------------------------------------------------------------
    def _move(self, msg: Move) -> MoveResult:
        return self.devices.rig.move_to(
            np.asarray(msg.wi, dtype=np.float64),
            np.asarray(msg.wo, dtype=np.float64),
            joints=msg.joints,
        )

    def _read(self, msg: Read) -> RigState:  # noqa: ARG002
        return self.devices.rig.read()

    def _settle(self, msg: Settle) -> None:
        if msg.seconds > 0:
            self.devices.sleep(msg.seconds)

    def _set_light(self, msg: SetLight) -> None:
        light = self.devices.light
        if light is None:
            raise CameraError(
                "the plan asks for dark frames (darks.count > 0) but this session has no "
                "switchable light; cap the lens and set darks.count = 0, or use a rig light"
            )
        light.set_light(msg.on)

    def _set_target(self, msg: SetTarget) -> None:
        if self.devices.target is not None:
            self.devices.target.set_target(msg.kind)
        elif msg.kind == "flat":
            raise CameraError(
                "the plan asks for flat frames ([flats] count > 0) but this session has no "
                "target changer to put the flat-field panel over the lens; set "
                "[flats] count = 0"
            )

    def _shoot(self, msg: Shoot) -> Captured:
        if self.session_dir is None:
            raise RuntimeError("this engine has no session directory to store frames in")
        camera = self.devices.camera
        if isinstance(camera, SeededShots):
            camera.next_shot(msg.step, msg.frame)
        clock = self.devices.clock
        rig_time = None if clock is None else float(clock())
        shot = camera.capture(msg.exposure_time, msg.iso, msg.f_number)
        name = msg.stem + (shot.suffix or ".raw")
        # On disk (renamed into place, fsynced) before the plan can journal it.
        write_atomic(self.session_dir / name, shot.data)
        return Captured(
            shot, name, sha256_bytes(shot.data), xxh3_bytes(shot.data), len(shot.data), rig_time
        )


# --------------------------------------------------------------------------------------
# One run: start, plan, fault, finalizer, stop


def fault_record(exc: BaseException, source: str) -> dict[str, Any]:
    """The ``fault`` document of a device error, its fields taken from the exception."""
    rec: dict[str, Any] = {"type": "fault", "source": source, "error": str(exc)}
    if isinstance(exc, RigFault):
        if exc.servo is not None:
            rec["servo"] = exc.servo
        rec["error_bits"] = exc.error_bits
    elif isinstance(exc, BusError):
        if exc.servo is not None:
            rec["servo"] = exc.servo
        if exc.cause is not None:
            rec["cause"] = exc.cause
    return rec


def finalize(devices: SessionDevices) -> dict[str, Any]:
    """Park, torque off, then light on and sample in place, whatever happened; report
    failures."""
    out: dict[str, Any] = {"parked": False, "torque_off": False}
    errors = []
    try:
        devices.rig.park()
        out["parked"] = True
    except Exception as exc:  # noqa: BLE001 - the finalizer must reach torque off
        errors.append(f"park: {exc}")
    try:
        unconfirmed = devices.rig.torque_off()
        # The journal must not claim a safe state nobody saw: a silent servo may still
        # hold torque (the broadcast write reached it, or not).
        out["torque_off"] = not unconfirmed
        if unconfirmed:
            out["torque_unconfirmed"] = list(unconfirmed)
            errors.append(f"torque off not confirmed by servo(s) {list(unconfirmed)}")
    except Exception as exc:  # noqa: BLE001
        errors.append(f"torque off: {exc}")
    # Light and target after the rig is safe: a target changer may be an operator asked
    # to swap the mirror back, who must not hold up the torque off.
    if devices.light is not None:
        with contextlib.suppress(Exception):
            devices.light.set_light(True)
    if devices.target is not None:
        with contextlib.suppress(Exception):
            devices.target.set_target("sample")
    if errors:
        out["finalizer_errors"] = errors
    return out


@dataclass
class RunOutcome:
    """How :func:`run_plan` ended: ``status`` (``completed``, ``fault``, ``interrupted``),
    the error that ended it, and the finalizer's report."""

    status: str
    error: BaseException | None = None
    finalizer: dict[str, Any] = field(default_factory=dict)


def run_plan(
    engine: Engine, plan: Generator[Any, Any, Any], start: Mapping[str, Any]
) -> RunOutcome:
    """Publish ``start``, execute ``plan``, journal a fault, always finalize, publish ``stop``."""
    status, error = "interrupted", None
    fin: dict[str, Any] = {"parked": False, "torque_off": False}
    with _terminate_as_interrupt():
        engine.publish(start)
        try:
            engine.execute(plan)
            status = "completed"
        except CameraError as exc:
            engine.publish(fault_record(exc, "camera"))
            status, error = "fault", exc
        except RigError as exc:  # RigFault, BusError, or a refusal no plan handled
            engine.publish(fault_record(exc, "rig"))
            status, error = "fault", exc
        except (KeyboardInterrupt, Interrupted) as exc:
            status, error = "interrupted", exc
        finally:
            fin = finalize(engine.devices)
            engine.publish({"type": "stop", "status": status, **fin})
    return RunOutcome(status, error, fin)
