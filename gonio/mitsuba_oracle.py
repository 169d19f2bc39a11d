"""Load Mitsuba 3 as an independent test and benchmark oracle.

Mitsuba is a *test* extra, not a runtime dependency, so it is imported lazily here and
nowhere else.  Its vectorised ``llvm_ad_rgb`` variant needs a matching system libLLVM
(19); with a wrong libLLVM the process *aborts* (exit 134, not an exception) on the first
JIT-compiled BSDF evaluation.  That is why the LLVM variant is probed in a throw-away
subprocess before this process touches it; ``scalar_rgb`` always works and is the
fallback.

>>> mi, variant = load_mitsuba()            # "llvm_ad_rgb" or "scalar_rgb"
>>> mi, variant = load_mitsuba("scalar")    # always "scalar_rgb"
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

__all__ = ["MitsubaUnavailableError", "LIBLLVM_CANDIDATES", "llvm_usable", "load_mitsuba"]

# Where Debian/Ubuntu's libllvm19 package installs the shared library.
LIBLLVM_CANDIDATES: tuple[str, ...] = (
    "/usr/lib/x86_64-linux-gnu/libLLVM-19.so",
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/llvm-19/lib/libLLVM-19.so",
    "/usr/lib/llvm-19/lib/libLLVM.so.1",
    "/usr/lib/aarch64-linux-gnu/libLLVM-19.so",
)

_PROBE_TIMEOUT_S = 300.0

# Evaluates a rough conductor once: the operation that aborts with a bad libLLVM.
_PROBE_CODE = """
import mitsuba as mi
mi.set_variant("llvm_ad_rgb")
b = mi.load_dict({"type": "roughconductor", "distribution": "ggx", "alpha": 0.2})
si = mi.SurfaceInteraction3f()
si.wi = mi.Vector3f(0.0, 0.6, 0.8)
v = b.eval(mi.BSDFContext(), si, mi.Vector3f(0.0, -0.6, 0.8))
import drjit as dr
x = float(dr.ravel(v[0])[0]) if hasattr(dr, "ravel") else float(v[0][0])
assert x > 0.0 and x == x, x
print("ok", x)
"""

_cache: dict[str, tuple[Any, str]] = {}
_llvm_probe: bool | None = None


class MitsubaUnavailableError(ImportError):
    """Mitsuba 3 is not installed (it is in the ``test`` extra)."""


def _find_libllvm() -> str | None:
    env = os.environ.get("DRJIT_LIBLLVM_PATH")
    if env and Path(env).is_file():
        return env
    for cand in LIBLLVM_CANDIDATES:
        if Path(cand).is_file():
            return cand
    return None


def _import_mitsuba() -> Any:
    try:
        import mitsuba as mi
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise MitsubaUnavailableError(
            "Mitsuba 3 is not installed; it is only needed as a test/benchmark oracle. "
            'Install it with: pip install -e ".[test]"  (or: pip install mitsuba)'
        ) from exc
    return mi


def llvm_usable() -> bool:
    """Whether ``llvm_ad_rgb`` can evaluate a rough conductor without crashing.

    Runs once per process in a subprocess (a bad libLLVM aborts the interpreter) and
    caches the answer.  Sets ``DRJIT_LIBLLVM_PATH`` in this process when libLLVM 19 is
    found, so a later ``set_variant("llvm_ad_rgb")`` here uses the same library.
    """
    global _llvm_probe
    if _llvm_probe is not None:
        return _llvm_probe
    lib = _find_libllvm()
    if lib is None:
        _llvm_probe = False
        return False
    env = dict(os.environ, DRJIT_LIBLLVM_PATH=lib)
    try:
        proc = subprocess.run(
            [sys.executable, "-c", _PROBE_CODE],
            env=env,
            capture_output=True,
            text=True,
            timeout=_PROBE_TIMEOUT_S,
        )
        ok = proc.returncode == 0 and proc.stdout.startswith("ok")
    except (OSError, subprocess.TimeoutExpired):
        ok = False
    if ok:
        os.environ["DRJIT_LIBLLVM_PATH"] = lib
    _llvm_probe = ok
    return ok


def load_mitsuba(prefer: str = "llvm") -> tuple[Any, str]:
    """Import Mitsuba 3 and select a variant.

    Parameters
    ----------
    prefer
        ``"llvm"``: the vectorised ``llvm_ad_rgb`` variant if libLLVM 19 is present and a
        subprocess probe (including a ``roughconductor`` evaluation) succeeds, otherwise
        ``"scalar_rgb"``.  ``"scalar"``: always ``"scalar_rgb"``.

    Returns
    -------
    (mi, variant)
        The ``mitsuba`` module with ``variant`` set (``mi.set_variant`` has been called).

    Raises
    ------
    MitsubaUnavailableError
        Mitsuba is not installed (an ``ImportError``).
    ValueError
        ``prefer`` is neither ``"llvm"`` nor ``"scalar"``.
    """
    if prefer not in ("llvm", "scalar"):
        raise ValueError(f"prefer must be 'llvm' or 'scalar', got {prefer!r}")
    if prefer in _cache:
        mi, variant = _cache[prefer]
        mi.set_variant(variant)
        return mi, variant
    if prefer == "llvm":
        # Import check first so that a missing Mitsuba gives the clear error, not a probe.
        if _find_libllvm() is not None:
            lib = _find_libllvm()
            os.environ.setdefault("DRJIT_LIBLLVM_PATH", lib)  # before drjit is imported
        mi = _import_mitsuba()
        variant = "llvm_ad_rgb" if llvm_usable() else "scalar_rgb"
    else:
        mi = _import_mitsuba()
        variant = "scalar_rgb"
    mi.set_variant(variant)
    _cache[prefer] = (mi, variant)
    return mi, variant
