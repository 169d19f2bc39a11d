"""The exceptions gonio raises on purpose.

Every error a user can provoke with bad input derives from :class:`GonioError`, so the
command line can print its message and exit non-zero instead of showing a traceback.
Messages name the file, field or value and say what was expected.
"""

from __future__ import annotations


class GonioError(Exception):
    """Base class of every deliberate gonio error."""


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
    """The servo rig cannot do what was asked (bad port, unreachable pose, ...)."""


class RigFault(RigError):
    """A servo reported a hardware fault or stopped answering; torque has been cut."""


class CameraError(GonioError):
    """A camera is missing, refused a setting, or failed to deliver a frame."""


class SessionError(GonioError):
    """A capture session cannot be started, resumed or reduced as asked."""


class FitError(GonioError):
    """A fit could not produce a sound result."""


class ReductionError(GonioError):
    """RAW frames could not be reduced to radiance or BRDF samples."""
