"""The device interfaces: what a session may ask of a rig, a camera, a light, a target.

Every backend (the Dynamixel rig over dynamixel-sdk, the rig over the in-process loopback
transport, the gphoto2 camera, the simulator's camera, light and target changer)
implements these small ``typing.Protocol``s directly, in the spirit of bluesky/ophyd's
``Movable``/``Readable``/``Stoppable`` and python-microscope's one-module device
interfaces.  A session asks for abilities with ``isinstance(dev, Light)``: a real rig's
light and target changer are separate hardware, not part of the camera, so each is its
own ability and a backend implements only those it has.

Nothing here moves or opens anything; the composition root (``gonio.app``) builds the
devices and hands them to the session engine (``gonio.capture``).

Failures are the typed exceptions of :mod:`gonio.errors`:
:class:`~gonio.errors.PoseRefused` (checked before anything moved, with a
:class:`~gonio.errors.RefusalReason`), :class:`~gonio.errors.BusError` (a servo did not
answer or answered garbage; the rig's state is unknown), :class:`~gonio.errors.RigFault`
(a servo reported a hardware error or a move timed out; torque has been cut) and
:class:`~gonio.errors.CameraError`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "Camera",
    "CameraInfo",
    "Light",
    "MoveResult",
    "MovableRig",
    "ReadableRig",
    "RigDevice",
    "RigState",
    "SeededShots",
    "Shot",
    "TargetChanger",
]


# --------------------------------------------------------------------------------------
# Rig


@dataclass(frozen=True)
class RigState:
    """One read of every servo of the rig.

    Attributes
    ----------
    joints
        Joint angles as the encoders report them, joint name -> rad.
    temperatures
        Servo temperatures, joint name -> degC.
    errors
        Hardware error bits (register 70 on X-series) per joint; 0 when healthy.
    moving
        Whether any servo reports that it is still moving.
    approach
        Sign of each joint's last commanded move in joint angle, joint name -> +1 (its
        angle increased), -1 (decreased) or 0 (unknown); a move within the position
        tolerance (the servo's deadband) keeps it.  Which side of its backlash a joint
        sits on (``gonio.rig.asbuilt``).
    """

    joints: dict[str, float]
    temperatures: dict[str, float] = field(default_factory=dict)
    errors: dict[str, int] = field(default_factory=dict)
    moving: bool = False
    approach: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class MoveResult:
    """Outcome of :meth:`MovableRig.move_to`.

    Attributes
    ----------
    wi, wo
        Requested directions (sample frame, unit vectors).
    wi_achieved, wo_achieved
        Directions computed from the read-back joint angles with the rig's kinematics.
    joints
        Read-back joint angles, joint name -> rad.
    error_i, error_o
        Angles between requested and achieved directions, rad.
    duration
        Time the move took, s (the servo clock's for a virtual rig, else the wall clock).
    """

    wi: NDArray[np.float64]
    wo: NDArray[np.float64]
    wi_achieved: NDArray[np.float64]
    wo_achieved: NDArray[np.float64]
    joints: dict[str, float]
    error_i: float
    error_o: float
    duration: float


@runtime_checkable
class ReadableRig(Protocol):
    """A rig whose state can be read without moving it."""

    def read(self) -> RigState:
        """Joints, temperatures and error bits of every servo.

        Raises
        ------
        BusError
            A servo did not answer.
        """
        ...


@runtime_checkable
class MovableRig(Protocol):
    """A rig that puts the light along ``wi`` and the camera along ``wo``."""

    def move_to(
        self, wi: ArrayLike, wo: ArrayLike, *, joints: Mapping[str, float] | None = None
    ) -> MoveResult:
        """Move and wait until every servo is in position.

        ``joints`` (joint name -> rad), when given, is the solution the dry run chose for
        this pose (from the previous pose of the same plan); the rig moves there after
        checking it again (limits, shadowing, clearance, path from where it is) instead
        of solving the inverse kinematics anew, so that the run does what the dry run
        showed.  Without it the rig solves for the least motion from where it is.

        Raises
        ------
        PoseRefused
            The request was checked and refused before anything moved (``reason`` says
            which rule: limits, shadowing, collision, path, ...).
        BusError
            A servo stopped answering; whether anything moved is unknown.
        RigFault
            A servo reported a hardware error, or the move timed out; torque is off.
        """
        ...

    def stop(self) -> None:
        """Stop any motion at once (from another thread or a signal handler)."""
        ...

    def park(self) -> dict[str, float]:
        """Move to the park pose, then cut torque; returns the read-back joints (rad)."""
        ...

    def torque_off(self) -> list[int]:
        """Cut torque on every servo; returns the IDs that did not confirm it."""
        ...


@runtime_checkable
class RigDevice(MovableRig, ReadableRig, Protocol):
    """Both abilities: what a capture session needs from its rig."""


# --------------------------------------------------------------------------------------
# Camera, light, target


@dataclass(frozen=True)
class Shot:
    """One captured frame as the camera delivered it.

    Attributes
    ----------
    data
        The file's bytes (RAW, unmodified).
    suffix
        File suffix with the dot, lower case (``".dng"``, ``".nef"``).
    exposure_time
        Exposure time actually used, s.
    iso
        ISO speed actually used (NaN if the camera does not say).
    f_number
        f-number actually used (NaN if the camera does not say).
    extra
        Backend details worth journaling (e.g. the camera's own file name, temperatures).
    """

    data: bytes
    suffix: str
    exposure_time: float
    iso: float
    f_number: float
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class CameraInfo:
    """What a camera reports about itself (recorded in the session manifest)."""

    backend: str
    model: str
    sensor_size_mm: tuple[float, float] | None = None
    settings: dict[str, Any] = field(default_factory=dict)
    serial: str | None = None

    def to_json(self) -> dict[str, Any]:
        doc = {
            "backend": self.backend,
            "model": self.model,
            "sensor_size_mm": list(self.sensor_size_mm) if self.sensor_size_mm else None,
            "settings": dict(self.settings),
        }
        # only when known: manifests of cameras without one stay as they were
        if self.serial is not None:
            doc["serial"] = self.serial
        return doc


@runtime_checkable
class Camera(Protocol):
    """A camera that shoots RAW frames.

    ``capture`` raises :class:`~gonio.errors.CameraError` when the camera is gone,
    refuses a setting or fails to deliver.  There is no seed here: a simulated camera
    gets its random generator at construction (see :class:`SeededShots`).
    """

    def describe(self) -> CameraInfo:
        """Backend, model and settings, for the session manifest."""
        ...

    def capture(self, exposure_time: float, iso: float | None, f_number: float | None) -> Shot:
        """Shoot one frame.

        Parameters
        ----------
        exposure_time
            Exposure time, s (the camera picks its nearest step and reports it).
        iso, f_number
            ISO speed and f-number; None leaves the camera's own setting.
        """
        ...

    def close(self) -> None:
        """Release the camera (idempotent)."""
        ...


@runtime_checkable
class Light(Protocol):
    """A switchable light source (a relay, a controllable LED driver, the simulator's)."""

    def set_light(self, on: bool) -> None:
        """Switch the light on or off and wait until it has settled."""
        ...


@runtime_checkable
class TargetChanger(Protocol):
    """Something that puts the reference target in place of the sample (or back)."""

    def set_target(self, kind: str) -> None:
        """``"sample"``, ``"reference"`` or ``"mirror"`` (the flat mirror of a rig
        calibration in the sample's place)."""
        ...


@runtime_checkable
class SeededShots(Protocol):
    """A simulated camera's extra ability: name the shot it is about to take.

    A simulated session is reproducible bit for bit from its seed, including a shot
    redone after a crash: the camera draws each shot's noise from a stream keyed by the
    session seed it was built with and the (step, frame) the engine names here.  Real
    cameras do not have this ability and the engine does not need it.
    """

    def next_shot(self, step: int, frame: int) -> None:
        """The next :meth:`Camera.capture` is frame ``frame`` of step ``step``."""
        ...
