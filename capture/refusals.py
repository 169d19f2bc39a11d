"""Interim: turn the kinematics' refusal sentences into typed :class:`PoseRefused`.

REMOVE WITH THE RIG MERGE.  The session engine tells a refused pose from a fault by
exception type only (:class:`~gonio.errors.PoseRefused` versus
:class:`~gonio.errors.BusError` / :class:`~gonio.errors.RigFault`).  Until the rig
engineer's branch lands, ``Kinematics.inverse`` still raises a plain
:class:`~gonio.errors.RigError` whose message says why; the dry-run rig
(:mod:`gonio.capture.schedule`) and the adapter of the old ``Rig``
(:mod:`gonio.app.legacy_rig`) call the kinematics themselves, *before* anything moves, and
convert what it refuses with :func:`as_refusal`.  No read-back and no threshold decide
anything: only errors raised by a check that moves nothing are converted.
"""

from __future__ import annotations

from gonio.errors import PoseRefused, RefusalReason, RigError

__all__ = ["as_refusal"]

#: Phrases of ``gonio.rig.kinematics`` (as of the contracts commit) -> reason, first match.
_PHRASES: tuple[tuple[str, RefusalReason], ...] = (
    ("not a finite non-zero direction", RefusalReason.INVALID_DIRECTION),
    ("sample holder's rim", RefusalReason.BEYOND_RIM),
    ("outside its limits", RefusalReason.JOINT_LIMIT),
    ("would shadow", RefusalReason.SHADOWING),
    ("arms would collide", RefusalReason.ARM_CLEARANCE),
    ("pass or touch", RefusalReason.PATH),
    ("pass each other", RefusalReason.PATH),
    ("cannot tilt far enough", RefusalReason.TILT_RANGE),
    ("are parallel", RefusalReason.NO_SOLUTION),
    ("no stage orientation", RefusalReason.NO_SOLUTION),
)


def as_refusal(exc: RigError) -> PoseRefused:
    """The :class:`PoseRefused` for a refusal raised by a kinematic check.

    Only call this on errors of a check that moved nothing (``Kinematics.inverse``,
    ``check_joints``, the path check); a :class:`PoseRefused` is returned as it is.
    """
    if isinstance(exc, PoseRefused):
        return exc
    text = str(exc)
    for phrase, reason in _PHRASES:
        if phrase in text:
            return PoseRefused(reason, text)
    return PoseRefused(RefusalReason.NO_SOLUTION, text)
