"""Kept for the reduction's imports only (``load_manifest``); the session engine is now
:mod:`gonio.capture.sessions` (API), :mod:`~gonio.capture.engine`,
:mod:`~gonio.capture.session_plan`, :mod:`~gonio.capture.schedule`,
:mod:`~gonio.capture.session_dir` and :mod:`~gonio.capture.manifest`.

Remove once ``gonio.capture.reduce`` and ``reduce_cli`` import
:func:`gonio.capture.manifest.load_manifest` (which validates the manifest on every read)
and ``tests/capture/test_plan.py`` imports :func:`gonio.capture.schedule.build_schedule`.
"""

from __future__ import annotations

from gonio.capture.manifest import MANIFEST, SCHEMA_VERSION, load_manifest
from gonio.capture.schedule import build_schedule
from gonio.capture.session_dir import JOURNAL
from gonio.capture.session_plan import RAW_DIR

__all__ = ["JOURNAL", "MANIFEST", "RAW_DIR", "SCHEMA_VERSION", "build_schedule", "load_manifest"]
