"""The messages a session plan yields to the engine (bluesky-style, but small).

A plan is a generator: it yields one of these, the engine executes it on the devices and
sends the result back into the generator (``reply = yield Move(...)``), or throws the
exception the device raised into it, so the plan can react -- the adaptive bracket to
the frame it just shot, the pose loop to a :class:`~gonio.errors.PoseRefused`.  A plan
never touches a device itself, which is what lets the dry run execute the very same plan
against the kinematics alone.

==================  =============================================  ======================
message             what the engine does                           reply
==================  =============================================  ======================
:class:`Move`       ``rig.move_to(wi, wo, joints=...)``            ``MoveResult``
:class:`Read`       ``rig.read()``                                 ``RigState``
:class:`Settle`     wait ``seconds`` (servo time on a virtual rig) None
:class:`SetLight`   ``light.set_light(on)``                        None
:class:`SetTarget`  ``target.set_target(kind)`` (if there is one)  None
:class:`Shoot`      name the shot, capture, write the RAW file     :class:`Captured`
                    atomically (the dry run replies None)
:class:`Emit`       publish a document (``shot``) to subscribers   the document as sent
:class:`Checkpoint` publish a step's closing document              the document as sent
                    (``pose_done`` / ``pose_skipped``)
==================  =============================================  ======================
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from gonio.devices import Shot

__all__ = [
    "Captured",
    "Checkpoint",
    "Emit",
    "Message",
    "Move",
    "Read",
    "SetLight",
    "SetTarget",
    "Settle",
    "Shoot",
]


@dataclass(frozen=True)
class Move:
    """Put the light along ``wi`` and the camera along ``wo`` (sample frame, unit).

    ``joints`` (rad) is the solution the dry run chose for ``step``; None lets the rig
    solve from where it is.
    """

    step: int
    wi: tuple[float, float, float]
    wo: tuple[float, float, float]
    joints: Mapping[str, float] | None = None


@dataclass(frozen=True)
class Read:
    """Read the rig's joints and temperatures."""


@dataclass(frozen=True)
class Settle:
    """Let the arms stop vibrating before the first shot, s."""

    seconds: float


@dataclass(frozen=True)
class SetLight:
    """Switch the light (off for dark frames)."""

    on: bool


@dataclass(frozen=True)
class SetTarget:
    """Put the sample or the reference target in place."""

    kind: str


@dataclass(frozen=True)
class Shoot:
    """Shoot frame ``frame`` of step ``step`` and store it as ``stem`` + the camera's
    suffix (a path relative to the session, e.g. ``raw/p0003_f01_sample``)."""

    step: int
    frame: int
    exposure_time: float
    iso: float | None
    f_number: float | None
    stem: str


@dataclass(frozen=True)
class Captured:
    """A stored frame: the shot as delivered, where it is, and its digests."""

    shot: Shot
    file: str
    sha256: str
    xxh3_128: str
    bytes: int
    #: Rig time (s) read just before the frame was shot (``SessionDevices.clock``), or
    #: None when the devices keep no clock.
    rig_time: float | None = None


@dataclass(frozen=True)
class Emit:
    """Publish a document (subscribers: the journal first, then progress displays)."""

    document: dict[str, Any]


@dataclass(frozen=True)
class Checkpoint:
    """Publish the document that closes a step; a resume restarts after the last one."""

    document: dict[str, Any]


Message = Move | Read | Settle | SetLight | SetTarget | Shoot | Emit | Checkpoint
