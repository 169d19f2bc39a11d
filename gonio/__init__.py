"""gonio: drive a gonioreflectometer, reduce RAW brackets to BRDF samples, fit BRDF models.

The core package holds what every subsystem shares: :mod:`gonio.radiometry`,
:mod:`gonio.brdf`, :mod:`gonio.errors` and the command line.  The subsystems
``gonio.rig``, ``gonio.capture``, ``gonio.fitting`` and ``gonio.simulator`` live in
their own top-level folders of the repository.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("gonio")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
