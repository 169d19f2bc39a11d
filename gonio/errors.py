"""The exceptions gonio raises on purpose.

Every error a user can provoke with bad input derives from :class:`GonioError`, so the
command line can print its message and exit non-zero instead of showing a traceback.
Messages name the file, field or value and say what was expected.
"""

from __future__ import annotations

from enum import StrEnum


def _rebuild(cls: type, args: tuple, state: dict) -> BaseException:
    """Unpickle a :class:`GonioError` without calling its ``__init__``."""
    err = cls.__new__(cls, *args)
    err.args = args
    err.__dict__.update(state)
    return err


class GonioError(Exception):
    """Base class of every deliberate gonio error.

    Picklable with its attributes whatever a subclass's constructor takes, so errors cross
    process boundaries (figure workers, dask workers) as themselves: the default pickling
    calls ``cls(*args)`` with the formatted message, which a constructor such as
    ``FileFormatError(path, message, field=)`` cannot take.
    """

    def __reduce__(self) -> tuple:
        return (_rebuild, (type(self), self.args, dict(self.__dict__)))


class ConfigError(GonioError, ValueError):
    """A configuration, plan or scene file (or field in one) is invalid."""


class ParameterError(GonioError, ValueError):
    """A model parameter is unknown, missing or outside its bounds."""


class UnknownNameError(GonioError, KeyError):
    """A name looked up in a registry (model, algorithm, backend) does not exist."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


class FileFormatError(GonioError, ValueError):
    """A data file is truncated, of the wrong format, or holds invalid values.

    Parameters
    ----------
    path
        The offending file.
    message
        What is wrong and what was expected.
    field
        The field, tag or record concerned, if any.
    """

    def __init__(self, path: object, message: str, field: str | None = None) -> None:
        self.path = str(path)
        self.field = field
        where = f"{self.path}" + (f", field '{field}'" if field else "")
        super().__init__(f"{where}: {message}")


class RigError(GonioError):
    """The servo rig cannot do what was asked (bad port, wrong configuration, ...).

    The session engine tells its three kinds apart by class, never by message:
    :class:`PoseRefused` (nothing moved; the pose can be skipped), :class:`BusError`
    (a servo did not answer; state unknown: a fault) and :class:`RigFault` (a servo
    reported a hardware error or a move timed out; torque is off: a fault).
    """


class RefusalReason(StrEnum):
    """Why a pose was refused before anything moved (the machine-readable part)."""

    #: wi or wo is not a finite, non-zero direction
    INVALID_DIRECTION = "invalid_direction"
    #: theta beyond the holder's rim (``geometry.max_theta_deg``)
    BEYOND_RIM = "beyond_rim"
    #: wi and wo parallel, or no stage orientation puts both at the arms' elevations
    NO_SOLUTION = "no_solution"
    #: the stage cannot tilt far enough
    TILT_RANGE = "tilt_range"
    #: a joint would leave its limits
    JOINT_LIMIT = "joint_limit"
    #: light and camera too close seen from the sample (one shadows the other)
    SHADOWING = "shadowing"
    #: the arms would collide (azimuth clearance)
    ARM_CLEARANCE = "arm_clearance"
    #: the move from the present pose would make the arms pass or touch
    PATH = "path"
    #: a goal pulse outside a servo's configured range
    PULSE_RANGE = "pulse_range"


class PoseRefused(RigError):
    """A pose was checked and refused before anything moved.

    Parameters
    ----------
    reason
        Which rule refused it.
    message
        The sentence for the user (names the joint, angle or limit).
    """

    def __init__(self, reason: RefusalReason, message: str) -> None:
        self.reason = RefusalReason(reason)
        super().__init__(message)


class BusError(RigError):
    """A servo did not answer, or answered garbage, after every retry.

    Parameters
    ----------
    message
        What was being done and what happened.
    servo
        The Dynamixel ID concerned, if one.
    cause
        ``"timeout"``, ``"corrupt"``, ``"device_error"``, ``"port"``, ...
    """

    def __init__(self, message: str, servo: int | None = None, cause: str | None = None) -> None:
        self.servo = servo
        self.cause = cause
        super().__init__(message)


class RigFault(RigError):
    """A servo reported a hardware fault, or a move timed out; torque has been cut.

    Parameters
    ----------
    message
        What happened and what to do.
    servo
        The Dynamixel ID that reported it (None for a timeout of several).
    error_bits
        The hardware error status bits (register 70), 0 when not a hardware error.
    """

    def __init__(self, message: str, servo: int | None = None, error_bits: int = 0) -> None:
        self.servo = servo
        self.error_bits = int(error_bits)
        super().__init__(message)


class CameraError(GonioError):
    """A camera is missing, refused a setting, or failed to deliver a frame."""


class SessionError(GonioError):
    """A capture session cannot be started, resumed or reduced as asked."""


class FitError(GonioError):
    """A fit could not produce a sound result."""


class ReductionError(GonioError):
    """RAW frames could not be reduced to radiance or BRDF samples."""
