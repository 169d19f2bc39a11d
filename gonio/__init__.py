"""gonio: drive a gonioreflectometer, reduce RAW brackets to BRDF samples, fit BRDF models.

The core package holds what every subsystem shares: :mod:`gonio.radiometry`,
:mod:`gonio.brdf`, :mod:`gonio.errors` and the command line.  The subsystems
``gonio.rig``, ``gonio.capture``, ``gonio.fitting`` and ``gonio.simulator`` live in
their own top-level folders of the repository.
"""

from __future__ import annotations

__all__ = ["__version__"]


def __getattr__(name: str) -> str:
    # Looked up on first use: importlib.metadata costs every `gonio` command ~20 ms of
    # start-up otherwise (issue 19: `gonio fit` under 2 s).
    if name != "__version__":
        raise AttributeError(f"module 'gonio' has no attribute {name!r}")
    from importlib.metadata import PackageNotFoundError, version

    try:
        v = version("gonio")
    except PackageNotFoundError:  # running from a source tree that was never installed
        v = "0.0.0+unknown"
    globals()["__version__"] = v
    return v
